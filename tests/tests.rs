//! The one integration-test binary: a module per area, each driving the real `hbmu` binary or
//! the library on real files (ripgrep's layout).

mod common;
mod dag;
mod ingest;
mod interop;
mod lab;
mod layout;
mod nightly;
mod report;
mod solid;
mod stages;
mod update;
