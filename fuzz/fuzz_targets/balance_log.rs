//! Fuzz target: the MT-SICS balance-log parser and the mass summary must never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let (readings, _findings) = hbmu::formats::balance_log::parse(data, "fuzz.log");
    let _ = hbmu::formats::balance_log::board_masses(&readings, Default::default());
});
