"""bams-cli: Bayesian adaptive multifidelity sampling over Parquet workspaces."""

__version__ = "0.1.0"
