"""Data in: measurements (CSV, dicts, DataFrames, Datasets), polarization-camera frames, synthetic image stacks."""
