//! Report graphics: line plots of training curves, Pareto plots of time against accuracy, the
//! Pareto front itself, and contact sheets of captioned renders.

pub mod contact_sheet;
pub mod pareto;
pub mod plot;
