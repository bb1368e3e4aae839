//! Meshes, their files (OBJ via tobj, glTF via gltf), ray queries through a BVH (obvhs),
//! closest-point queries (parry3d), area-weighted surface samples, the visual hull of a set of
//! masks (a starting shape when the data has no mesh), and checks of a mesh's health (topology,
//! folds through itself).

pub mod atlas;
pub mod bvh;
pub mod bvh8;
pub mod closest_point;
pub mod enclosed_surface;
pub mod bvh_wide;
pub mod gltf_io;
pub mod hull;
pub mod manifold;
pub mod mask_distance;
pub mod icosphere;
pub mod inward_surface;
pub mod iso_surface;
pub mod ground_truth;
pub mod materials_json;
pub mod mesh;
pub mod obj;
pub mod primitives;
pub mod remesh;
pub mod surface_samples;
pub mod tangents;
pub mod texture_file;

pub use mesh::{Mesh, Part};
