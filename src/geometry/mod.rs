//! Meshes, their files (OBJ via tobj, glTF via gltf), and ray queries through a BVH (obvhs).

pub mod atlas;
pub mod bvh;
pub mod bvh_wide;
pub mod gltf_io;
pub mod mesh;
pub mod obj;
pub mod primitives;
pub mod texture_file;

pub use mesh::{Mesh, Part};
