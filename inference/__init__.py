"""Inference: the BP-HMM MCMC kernel and its moves, fit, results, diagnostics, metrics, CLI."""
