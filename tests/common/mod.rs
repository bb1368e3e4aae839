//! Helpers shared by the integration tests (each test file that needs one says `mod common;`).
#![allow(dead_code)]

pub mod shared_data;
