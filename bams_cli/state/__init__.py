"""Workspace state: Parquet schemas and atomic reads and writes."""
