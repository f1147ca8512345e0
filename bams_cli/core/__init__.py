"""Pure numerical code: numpy/scipy/sklearn only, no paths, no Parquet, no CLI."""
