//! The spec, row types, reader and writer of pair's pairs.parquet and presence.parquet.
