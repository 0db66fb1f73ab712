//! Fuzz target: the measurement-sheet parser must never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = hbmu::formats::sheet::parse(data, "fuzz.csv");
});
