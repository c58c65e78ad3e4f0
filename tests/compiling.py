"""Compile options for the suite's few run-bound programs.

The test processes compile with LLVM's lowest optimisation level (``conftest.py``'s XLA flags):
most test programs run a few sweeps, so compiling is their cost. A program that samples long
(a Geweke or posterior-frequency test: thousands of sweeps) runs about three times slower so;
``jax.jit(f, compiler_options=RUN_BOUND)`` compiles it at XLA's default level instead (measured:
the joint-distribution test 36 s -> 27 s, one process, nothing else running).
"""

RUN_BOUND = {"xla_backend_optimization_level": 2}
