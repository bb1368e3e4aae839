//! A cube-map environment light (linear RGB radiance).

use glam::Vec3;

/// Six square faces of `res`² texels, face-major then row-major. Face order and orientation are
/// OpenGL's (+x, −x, +y, −y, +z, −z), in the dataset's world frame.
#[derive(Clone, Debug)]
pub struct CubeMap {
    pub res: usize,
    pub data: Vec<Vec3>,
}
