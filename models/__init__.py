"""Probability: HMM inference on arrays, emission models, and the BP-HMM NumPyro model."""
