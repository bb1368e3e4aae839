//! Report graphics: line plots of training curves, Pareto plots of time against accuracy, and the
//! Pareto front itself.

pub mod pareto;
pub mod plot;
