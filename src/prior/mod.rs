//! Per-view material labels that guide the optimisation: the IDArb network, label files, the
//! ground truth (oracle) and simulated IDArb labels, behind one `Prior` trait.

pub mod idarb;
pub mod idarb_sim;
pub mod labels_dir;
pub mod oracle;
pub mod source;
pub mod view_labels;

pub use view_labels::ViewLabels;
