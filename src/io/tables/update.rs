//! The spec, row types, reader and writer of update's tables (both steps).
