//! NeRF / NeRFactor pinhole camera: camera-to-world matrix with an OpenGL camera
//! (x right, y up, looking down −z), horizontal field of view `camera_angle_x`.

use glam::{Mat4, Vec2, Vec3};

#[derive(Clone, Debug)]
pub struct Camera {
    /// Camera-to-world transform.
    pub c2w: Mat4,
    /// Horizontal field of view in radians.
    pub fov_x: f32,
    pub width: usize,
    pub height: usize,
}

impl Camera {
    /// A camera at `eye` looking at `target` with `up` roughly up (builds the OpenGL c2w frame).
    pub fn look_at(eye: Vec3, target: Vec3, up: Vec3, fov_x: f32, width: usize, height: usize) -> Camera {
        let back = (eye - target).normalize();
        let right = up.cross(back).normalize();
        let true_up = back.cross(right);
        let c2w = Mat4::from_cols(right.extend(0.0), true_up.extend(0.0), back.extend(0.0), eye.extend(1.0));
        Camera { c2w, fov_x, width, height }
    }

    /// Focal length in pixels (square pixels, principal point at the image centre).
    pub fn focal(&self) -> f32 {
        0.5 * self.width as f32 / (0.5 * self.fov_x).tan()
    }

    pub fn origin(&self) -> Vec3 {
        self.c2w.w_axis.truncate()
    }

    /// The camera's forward direction in world space (its −z axis).
    pub fn forward(&self) -> Vec3 {
        -self.c2w.z_axis.truncate().normalize()
    }

    /// Unit world-space direction through continuous pixel coordinates (x right, y down;
    /// pixel (i, j) has its centre at (i + 0.5, j + 0.5)).
    pub fn ray_dir(&self, px: f32, py: f32) -> Vec3 {
        let f = self.focal();
        let d = Vec3::new(
            (px - 0.5 * self.width as f32) / f,
            -(py - 0.5 * self.height as f32) / f,
            -1.0,
        );
        self.c2w.transform_vector3(d).normalize()
    }

    /// Continuous pixel coordinates of a world point and its planar depth along the view axis
    /// (positive in front of the camera).
    pub fn project(&self, p: Vec3) -> (Vec2, f32) {
        let q = self.c2w.inverse().transform_point3(p);
        let depth = -q.z;
        let f = self.focal();
        let x = 0.5 * self.width as f32 + f * q.x / depth;
        let y = 0.5 * self.height as f32 - f * q.y / depth;
        (Vec2::new(x, y), depth)
    }

    /// World-to-camera rotation: takes world vectors into the OpenGL camera frame
    /// (used for camera-space normals such as IDArb's).
    pub fn world_to_camera_dir(&self, v: Vec3) -> Vec3 {
        self.c2w.inverse().transform_vector3(v)
    }

    /// The world size of one pixel at `p`'s depth.
    pub fn pixel_footprint_at(&self, p: Vec3) -> f32 {
        self.project(p).1.abs() / self.focal()
    }

    /// The same camera at another resolution (same field of view).
    pub fn resized(&self, width: usize, height: usize) -> Camera {
        Camera { width, height, ..self.clone() }
    }
}

/// The median over `cameras` of the world size of one pixel at `p`'s depth: the scale at which
/// the views resolve an object centred there (the hull's voxels and the meshes' edges are sized
/// in it).
pub fn median_pixel_footprint<'a>(cameras: impl IntoIterator<Item = &'a Camera>, p: Vec3) -> f32 {
    let mut sizes: Vec<f32> = cameras.into_iter().map(|c| c.pixel_footprint_at(p)).collect();
    if sizes.is_empty() {
        return f32::NAN;
    }
    sizes.sort_by(f32::total_cmp);
    sizes[sizes.len() / 2]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn look_down_neg_z() -> Camera {
        Camera { c2w: Mat4::from_translation(Vec3::new(0.0, 0.0, 4.0)), fov_x: 90f32.to_radians(), width: 100, height: 100 }
    }

    #[test]
    fn axis_points_project_where_expected() {
        let cam = look_down_neg_z();
        let (p, d) = cam.project(Vec3::ZERO);
        assert!((p - Vec2::new(50.0, 50.0)).length() < 1e-4 && (d - 4.0).abs() < 1e-5);
        // fov 90°: x = depth lands on the right edge; +y world is up, i.e. row 0.
        let (p, _) = cam.project(Vec3::new(4.0, 0.0, 0.0));
        assert!((p.x - 100.0).abs() < 1e-3);
        let (p, _) = cam.project(Vec3::new(0.0, 4.0, 0.0));
        assert!(p.y.abs() < 1e-3);
    }

    #[test]
    fn ray_and_projection_are_inverse() {
        let cam = Camera::look_at(Vec3::new(2.0, -3.0, 1.5), Vec3::ZERO, Vec3::Z, 0.69, 256, 256);
        assert!((cam.forward() - (-cam.origin()).normalize()).length() < 1e-5);
        let d = cam.ray_dir(37.5, 200.25);
        let (p, depth) = cam.project(cam.origin() + 3.0 * d);
        assert!((p - Vec2::new(37.5, 200.25)).length() < 1e-3 && depth > 0.0);
    }
}
