//! Locate: posterior-predictive checks of the updated model against the recordings.
