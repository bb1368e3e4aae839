//! NeRF / NeRFactor pinhole camera: camera-to-world matrix with an OpenGL camera
//! (x right, y up, looking down −z), horizontal field of view `camera_angle_x`.

use glam::{Mat3, Mat4, Vec2, Vec3, Vec4};

/// How far a camera-to-world matrix's rotation part may be from orthonormal (largest entry of
/// RᵀR − I, and |det R − 1|) and its bottom row from (0, 0, 0, 1). Matrices stored with 6–7
/// significant digits (NeRF's and NeRFactor's JSON) are orthonormal to ~5e-7 (measured on the shared
/// hotdog's 116 frames); a 1e-3 scale error moves a ray at the border of an 800-pixel view by 0.4
/// pixel, so anything beyond it is not a rounding of a rigid pose but a different camera model
/// (scale, shear, mirror) the renderers do not implement.
pub const RIGID_TOLERANCE: f32 = 1e-3;

/// Why `c2w` is not a rigid transform (rotation + translation) within [`RIGID_TOLERANCE`], or None.
pub fn rigid_problem(c2w: &Mat4) -> Option<String> {
    let cols = c2w.to_cols_array();
    if let Some(v) = cols.iter().find(|v| !v.is_finite()) {
        return Some(format!("it holds a non-finite value ({v})"));
    }
    let bottom = c2w.row(3);
    if (bottom - Vec4::new(0.0, 0.0, 0.0, 1.0)).abs().max_element() > RIGID_TOLERANCE {
        return Some(format!("its bottom row is {:?}, not (0, 0, 0, 1)", bottom.to_array()));
    }
    let r = Mat3::from_mat4(*c2w);
    let gram = r.transpose() * r - Mat3::IDENTITY;
    let off = gram.to_cols_array().iter().fold(0.0f32, |m, v| m.max(v.abs()));
    if off > RIGID_TOLERANCE {
        let scales = [r.x_axis.length(), r.y_axis.length(), r.z_axis.length()];
        return Some(format!(
            "its rotation part is not orthonormal (RᵀR differs from I by {off:.2e} > {RIGID_TOLERANCE:e}; axis lengths {scales:?}): scale or shear"
        ));
    }
    let det = r.determinant();
    if (det - 1.0).abs() > RIGID_TOLERANCE {
        return Some(format!("its rotation part has determinant {det:.4}, not +1 (a mirror)"));
    }
    None
}

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
    /// (positive in front of the camera). For many points, take [`Camera::projector`] once.
    pub fn project(&self, p: Vec3) -> (Vec2, f32) {
        self.projector().project(p)
    }

    /// The projection with the world-to-camera transform inverted once, for projecting many points.
    pub fn projector(&self) -> Projector {
        Projector { w2c: self.c2w.inverse(), focal: self.focal(), centre: Vec2::new(0.5 * self.width as f32, 0.5 * self.height as f32) }
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

/// A camera's pinhole projection, ready to apply: [`Camera::project`] without inverting the pose
/// per point.
#[derive(Clone, Copy, Debug)]
pub struct Projector {
    pub w2c: Mat4,
    /// Focal length in pixels.
    pub focal: f32,
    /// The image centre in pixel coordinates (the principal point).
    pub centre: Vec2,
}

impl Projector {
    /// Continuous pixel coordinates (x right, y down) of a world point and its planar depth along
    /// the view axis (positive in front of the camera).
    pub fn project(&self, p: Vec3) -> (Vec2, f32) {
        let q = self.w2c.transform_point3(p);
        let depth = -q.z;
        (Vec2::new(self.centre.x + self.focal * q.x / depth, self.centre.y - self.focal * q.y / depth), depth)
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
    fn rigid_poses_pass_and_scaled_sheared_mirrored_or_projective_ones_are_named() {
        let cam = Camera::look_at(Vec3::new(2.0, -3.0, 1.5), Vec3::ZERO, Vec3::Z, 0.69, 8, 8);
        assert_eq!(rigid_problem(&cam.c2w), None);
        let scaled = cam.c2w * Mat4::from_scale(Vec3::splat(1.01));
        assert!(rigid_problem(&scaled).unwrap().contains("not orthonormal"));
        let mirrored = cam.c2w * Mat4::from_scale(Vec3::new(-1.0, 1.0, 1.0));
        assert!(rigid_problem(&mirrored).unwrap().contains("determinant"));
        let mut sheared = cam.c2w;
        sheared.y_axis += 0.1 * sheared.x_axis;
        assert!(rigid_problem(&sheared).unwrap().contains("not orthonormal"));
        let mut projective = cam.c2w;
        projective.x_axis.w = 0.5;
        assert!(rigid_problem(&projective).unwrap().contains("bottom row"));
        let mut nan = cam.c2w;
        nan.w_axis.x = f32::NAN;
        assert!(rigid_problem(&nan).unwrap().contains("non-finite"));
        // Rounding to 6 digits, as the JSON files store poses, stays within the tolerance.
        let rounded = Mat4::from_cols_array(&cam.c2w.to_cols_array().map(|v| (v * 1e6).round() / 1e6));
        assert_eq!(rigid_problem(&rounded), None);
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
