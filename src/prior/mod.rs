//! Per-view material labels that guide the optimisation (IDArb network, cached files, simulated).

pub mod idarb;
