"""Benchmarks of jaxtable against numpy/scipy baselines (`python -m benchmarks`,
`jaxtable bench`)."""
