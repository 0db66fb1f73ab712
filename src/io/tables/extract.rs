//! The spec, row types, reader and writer of extract's modes.parquet and point_flags.parquet.
