//! The spec, row types, reader and writer of report's table2 and intervals tables.
