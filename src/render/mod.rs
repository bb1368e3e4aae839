//! Renderers: G-buffer, split-sum shading, Monte Carlo shading, and the effects a scene switches on.

pub mod denoise;
pub mod effects;
pub mod gbuffer;
pub mod gbuffer_raster;
pub mod montecarlo;
pub mod montecarlo_op;
pub mod sh_light;
pub mod silhouette_op;
pub mod ray_count;
pub mod splitsum;
pub mod splitsum_op;
pub mod surface_op;
pub mod vertex_normals_op;
pub mod view;
