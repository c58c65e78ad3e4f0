"""Test-session settings: float64, and JAX's persistent compilation cache so that the many
samplers the tests build (identical programs around different objects) compile once."""

import os
import tempfile

import jax

jax.config.update("jax_enable_x64", True)
os.environ.setdefault("NPBRS_CACHE_DIR", "off")  # the command line, run in this process, keeps the cache below
_cache = os.environ.get("NPBRS_TEST_JAX_CACHE") or os.path.join(tempfile.gettempdir(), "npbrs-test-jax-cache")
jax.config.update("jax_compilation_cache_dir", _cache)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
