//! Optimisation of materials and light on fixed geometry (NVDiffRecMC's second pass): the
//! parameters, the training views, the differentiable batch render, the loss, the loop with
//! checkpoints, and the exports; and the geometry pass that comes before it when the shape is
//! reconstructed (`geometry_pass`), with an optional gentle refinement of its vertices in this
//! pass (`vertex_refinement`). The model they implement: docs/model.md. Evaluation: `eval`.

pub mod batch_render;
pub mod checkpoint;
pub mod config;
pub mod export;
pub mod fitter;
pub mod geometry_pass;
pub mod history;
pub mod labels;
pub mod objective;
pub mod parameters;
pub mod pixel_scatter;
pub mod settings_diff;
pub mod training_view;
pub mod vertex_refinement;
pub mod view_loss_op;
pub mod view_screening;
