//! The spec, row types, reader and writer of propagate's predictions.parquet.
