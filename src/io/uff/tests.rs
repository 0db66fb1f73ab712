//! Unit tests of the UFF reader and writer.
