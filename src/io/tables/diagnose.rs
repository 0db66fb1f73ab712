//! The spec, row types, reader and writer of diagnose's diagnosis and diagnosis_modes tables.
