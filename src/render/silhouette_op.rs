//! Analytic antialiasing of silhouettes (the scheme of nvdiffrast's `antialias`, on our ray-cast
//! G-buffer): the operator that gives vertex positions a gradient from the outline, where the
//! coverage of pixels changes as the mesh moves (source (b) of position gradients).
//!
//! A ray-cast image is a step function of the vertices: moving an outline changes which pixel
//! centres it covers, never a pixel's value continuously. For every pair of horizontally or
//! vertically adjacent pixels whose triangle ids differ, take the nearer one ("front"; the
//! background is infinitely far) and look for an edge of its triangle that is a silhouette edge
//! (a boundary edge, or one whose neighbouring triangle folds to the same side in the image, so
//! that the surface turns away there) and crosses the segment between the two pixel centres, at a
//! fraction s of the way from the front centre. Then, along that segment, the front surface
//! covers the back pixel's half by s − ½ (when s > ½) or leaves (½ − s) of the front pixel's half
//! to the back surface (when s < ½), and the colours are blended by that amount:
//!   s > ½:  out_back  += (s − ½)·(c_front − c_back)
//!   s < ½:  out_front += (½ − s)·(c_back − c_front)
//! Both are continuous at s = ½ and have the same derivative ∂out/∂s = c_front − c_back, which
//! flows to the edge's two end points through the crossing point and the perspective projection.
//! Only the first qualifying edge of a pair counts (as nvdiffrast). The pair's triangle ids and
//! depths are fixed for the step (the G-buffer's choice carries no gradient).
//!
//! Inputs (all f32 or all f64): the image [H·W, C] (any channels: colour over the background and
//! coverage, typically RGBA), positions [V, 3]. Output [H·W, C]: the antialiased image.

use std::collections::HashMap;
use std::sync::Arc;

use candle_core::{Result, Tensor};
use glam::{DMat4, DVec2, DVec3};

use crate::optim::tape::{apply, Kernel, Real};
use crate::render::gbuffer::GBuffer;
use crate::scene::Camera;

/// No triangle: the background in `triangle_of`, a boundary in `opposite`.
pub const NONE: u32 = u32::MAX;

/// For each triangle edge e (corners e and e+1 mod 3), the third vertex of the triangle across
/// it, or [`NONE`] where the edge is a boundary or shared by more than two triangles (both are
/// treated as possible silhouettes). Built once per connectivity.
#[derive(Clone, Debug)]
pub struct EdgeTopology {
    pub opposite: Arc<[[u32; 3]]>,
}

impl EdgeTopology {
    pub fn new(triangles: &[[u32; 3]]) -> Self {
        let mut edges: HashMap<(u32, u32), Vec<(usize, usize)>> = HashMap::with_capacity(triangles.len() * 3 / 2);
        for (t, tri) in triangles.iter().enumerate() {
            for e in 0..3 {
                let (a, b) = (tri[e], tri[(e + 1) % 3]);
                edges.entry((a.min(b), a.max(b))).or_default().push((t, e));
            }
        }
        let mut opposite = vec![[NONE; 3]; triangles.len()];
        for users in edges.values() {
            if let [(t0, e0), (t1, e1)] = users.as_slice() {
                opposite[*t0][*e0] = triangles[*t1][(e1 + 2) % 3];
                opposite[*t1][*e1] = triangles[*t0][(e0 + 2) % 3];
            }
        }
        EdgeTopology { opposite: opposite.into() }
    }
}

/// The pinhole projection in f64 (pixel coordinates x right, y down, as `Camera::project`).
#[derive(Clone, Copy, Debug)]
struct Projection {
    w2c: DMat4,
    focal: f64,
    cx: f64,
    cy: f64,
}

impl Projection {
    fn new(camera: &Camera) -> Self {
        Projection {
            w2c: camera.c2w.as_dmat4().inverse(),
            focal: camera.focal() as f64,
            cx: 0.5 * camera.width as f64,
            cy: 0.5 * camera.height as f64,
        }
    }

    /// Pixel coordinates and camera-space point (None behind or at the camera plane).
    fn project(&self, p: DVec3) -> Option<(DVec2, DVec3)> {
        let q = self.w2c.transform_point3(p);
        let z = -q.z;
        (z > 0.0).then(|| (DVec2::new(self.cx + self.focal * q.x / z, self.cy - self.focal * q.y / z), q))
    }

    /// World-space gradient of a scalar with pixel-coordinate gradient `g` at camera point `q`.
    fn adjoint(&self, q: DVec3, g: DVec2) -> DVec3 {
        let z = -q.z;
        let f = self.focal;
        // sx = cx + f·qx/z, sy = cy − f·qy/z, z = −qz.
        let g_q = DVec3::new(g.x * f / z, -g.y * f / z, g.x * f * q.x / (z * z) - g.y * f * q.y / (z * z));
        glam::DMat3::from_mat4(self.w2c).transpose() * g_q
    }
}

/// The fixed data of one view's antialiasing: its G-buffer's triangle ids and depths.
#[derive(Clone)]
pub struct Silhouettes {
    width: usize,
    height: usize,
    projection: Projection,
    triangle_of: Arc<[u32]>,
    triangles: Arc<[[u32; 3]]>,
    topology: EdgeTopology,
    /// The adjacent pixel pairs whose triangle ids differ, as (front, back, horizontal), in
    /// row-major order of the first pixel: fixed with the G-buffer, so found once, not per pass.
    pairs: Arc<[(u32, u32, bool)]>,
}

/// One pixel pair's blend: `to` receives w·(c_from − c_to); `s_sign` = ±1 is ∂w/∂s.
struct Blend {
    to: usize,
    from: usize,
    w: f64,
    s_sign: f64,
    /// Mesh vertices of the crossing edge and ∂s/∂(their world positions).
    verts: [usize; 2],
    ds_dp: [DVec3; 2],
}

impl Silhouettes {
    pub fn new(camera: &Camera, gbuffer: &GBuffer, triangles: Arc<[[u32; 3]]>, topology: EdgeTopology) -> Self {
        let triangle_of: Vec<u32> = gbuffer.surfels.iter().map(|s| s.map_or(NONE, |s| s.triangle)).collect();
        let depth: Vec<f32> = gbuffer.surfels.iter().map(|s| s.map_or(f32::INFINITY, |s| s.depth)).collect();
        let (w, h) = (gbuffer.width, gbuffer.height);
        let mut pairs = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let a = y * w + x;
                for (b, horizontal) in [(x + 1 < w).then(|| (a + 1, true)), (y + 1 < h).then(|| (a + w, false))].into_iter().flatten() {
                    if triangle_of[a] == triangle_of[b] {
                        continue;
                    }
                    let (front, back) = if depth[a] <= depth[b] { (a, b) } else { (b, a) };
                    pairs.push((front as u32, back as u32, horizontal));
                }
            }
        }
        Silhouettes {
            width: gbuffer.width,
            height: gbuffer.height,
            projection: Projection::new(camera),
            triangle_of: triangle_of.into(),
            triangles,
            topology,
            pairs: pairs.into(),
        }
    }

    /// The blends of every adjacent pixel pair at the current positions.
    fn blends<T: Real>(&self, positions: &[T]) -> Vec<Blend> {
        let p = |i: usize| DVec3::new(positions[3 * i].to_f64(), positions[3 * i + 1].to_f64(), positions[3 * i + 2].to_f64());
        self.pairs.iter().filter_map(|&(front, back, horizontal)| self.pair_blend(front as usize, back as usize, horizontal, &p)).collect()
    }

    fn pair_blend(&self, front: usize, back: usize, horizontal: bool, p: &impl Fn(usize) -> DVec3) -> Option<Blend> {
        let t = self.triangle_of[front] as usize;
        let tri = self.triangles[t].map(|i| i as usize);
        let proj = tri.map(|i| self.projection.project(p(i)));
        let centre = |i: usize| DVec2::new((i % self.width) as f64 + 0.5, (i / self.width) as f64 + 0.5);
        let (cf, cb) = (centre(front), centre(back));
        // Work in (along, across) coordinates of the segment: along = x for horizontal pairs.
        let swap = |v: DVec2| if horizontal { v } else { DVec2::new(v.y, v.x) };
        let (f, b) = (swap(cf), swap(cb));
        let dir = b.x - f.x; // ±1
        for e in 0..3 {
            let (ia, ib, ic) = (e, (e + 1) % 3, (e + 2) % 3);
            let (Some((sa, qa)), Some((sb, qb)), Some((sc, _))) = (proj[ia], proj[ib], proj[ic]) else { continue };
            if !self.is_silhouette(t, e, sa, sb, sc, p) {
                continue;
            }
            let (a2, b2) = (swap(sa), swap(sb));
            let dy = b2.y - a2.y;
            if dy == 0.0 || (a2.y - f.y) * (b2.y - f.y) > 0.0 {
                continue;
            }
            let u = (f.y - a2.y) / dy;
            let dx = b2.x - a2.x;
            let cross = a2.x + u * dx;
            let s = (cross - f.x) / dir;
            if !(0.0..=1.0).contains(&s) {
                continue;
            }
            // ∂cross/∂(a2, b2), then back to image axes, then through the projection.
            let d_a = DVec2::new(1.0 - u, dx * (u - 1.0) / dy) / dir;
            let d_b = DVec2::new(u, -dx * u / dy) / dir;
            let ds_dp = [self.projection.adjoint(qa, swap(d_a)), self.projection.adjoint(qb, swap(d_b))];
            let verts = [tri[ia], tri[ib]];
            return Some(if s >= 0.5 {
                Blend { to: back, from: front, w: s - 0.5, s_sign: 1.0, verts, ds_dp }
            } else {
                Blend { to: front, from: back, w: 0.5 - s, s_sign: -1.0, verts, ds_dp }
            });
        }
        None
    }

    /// Whether edge e of triangle t (projected end points sa, sb; third corner sc) can be an
    /// outline: a boundary, or the neighbour's third vertex projects to the same side as sc.
    fn is_silhouette(&self, t: usize, e: usize, sa: DVec2, sb: DVec2, sc: DVec2, p: &impl Fn(usize) -> DVec3) -> bool {
        let other = self.topology.opposite[t][e];
        if other == NONE {
            return true;
        }
        let Some((so, _)) = self.projection.project(p(other as usize)) else { return true };
        let side = |q: DVec2| (sb - sa).perp_dot(q - sa);
        side(sc) * side(so) > 0.0
    }
}

impl Kernel for Silhouettes {
    fn name(&self) -> &'static str {
        "silhouette-antialias"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        let n = self.width * self.height;
        let ok = shapes.len() == 2 && shapes[0].len() == 2 && shapes[0][0] == n && shapes[1].len() == 2 && shapes[1][1] == 3;
        if !ok {
            return Err(candle_core::Error::Msg(format!("silhouette-antialias: expected image [{n}, C] and positions [V, 3], got {shapes:?}")));
        }
        Ok(shapes[0].to_vec())
    }

    fn forward<T: Real>(&self, x: &[&[T]], shapes: &[&[usize]], out: &mut [T]) -> Result<()> {
        let (img, c) = (x[0], shapes[0][1]);
        out.copy_from_slice(img);
        for bl in self.blends(x[1]) {
            for ch in 0..c {
                let d = bl.w * (img[c * bl.from + ch].to_f64() - img[c * bl.to + ch].to_f64());
                out[c * bl.to + ch] += T::from_f64(d);
            }
        }
        Ok(())
    }

    fn backward<T: Real>(&self, x: &[&[T]], shapes: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let (img, c) = (x[0], shapes[0][1]);
        let blends = self.blends(x[1]);
        let [g_img, g_pos] = grads else { unreachable!("two inputs") };
        if let Some(gi) = g_img.as_deref_mut() {
            gi.copy_from_slice(g);
            for bl in &blends {
                for ch in 0..c {
                    let go = g[c * bl.to + ch];
                    gi[c * bl.from + ch] += T::from_f64(bl.w) * go;
                    gi[c * bl.to + ch] -= T::from_f64(bl.w) * go;
                }
            }
        }
        if let Some(gp) = g_pos.as_deref_mut() {
            for bl in &blends {
                // ∂L/∂s = Σ_ch g_to · (c_from − c_to) · ∂w/∂s, with c_from − c_to = ±(c_front − c_back).
                let g_s: f64 = (0..c)
                    .map(|ch| g[c * bl.to + ch].to_f64() * (img[c * bl.from + ch].to_f64() - img[c * bl.to + ch].to_f64()))
                    .sum::<f64>()
                    * bl.s_sign;
                for (v, d) in bl.verts.iter().zip(&bl.ds_dp) {
                    for k in 0..3 {
                        gp[3 * v + k] += T::from_f64(g_s * d[k]);
                    }
                }
            }
        }
        Ok(())
    }
}

/// The antialiased image [H·W, C] of `image` (one view's G-buffer order), on the tape.
pub fn antialias(op: Silhouettes, image: &Tensor, positions: &Tensor) -> Result<Tensor> {
    apply(op, &[image, positions])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::bvh::Bvh;
    use crate::geometry::primitives::MeshBuilder;
    use crate::geometry::Mesh;
    use crate::material::{BaseColor, PartMaterial, Scalar};
    use crate::optim::gradcheck::{check_gradient_with, GradCheckOptions};
    use crate::rng::Sampler;
    use candle_core::Device;
    use glam::{Quat, Vec3};

    fn blob() -> Mesh {
        let mut b = MeshBuilder::new();
        let part = b.part(PartMaterial { name: "m".into(), base_color: BaseColor::Constant(Vec3::splat(0.5)), roughness: Scalar::Constant(0.5), metallic: Scalar::Constant(0.0) });
        b.ellipsoid(part, Vec3::new(0.1, 0.0, 0.0), Vec3::new(1.0, 0.7, 0.8), Quat::from_rotation_z(0.3), 8, 6);
        b.build()
    }

    fn setup(mesh: &Mesh, camera: &Camera) -> (Silhouettes, Tensor, Tensor) {
        let bvh = Bvh::build(mesh);
        let gbuf = GBuffer::trace(mesh, &bvh, camera);
        let tris: Arc<[[u32; 3]]> = mesh.triangles.clone().into();
        let op = Silhouettes::new(camera, &gbuf, tris.clone(), EdgeTopology::new(&tris));
        let mut rng = Sampler::new(3, 0);
        let n = camera.width * camera.height;
        // Covered pixels get a random colour and coverage 1, the background its own colour and 0.
        let img: Vec<f64> = gbuf
            .surfels
            .iter()
            .flat_map(|s| {
                let c = [rng.next_f32() as f64, rng.next_f32() as f64, rng.next_f32() as f64];
                let a = if s.is_some() { 1.0 } else { 0.0 };
                [c[0], c[1], c[2], a]
            })
            .collect();
        let pos: Vec<f64> = mesh.positions.iter().flat_map(|p| p.to_array().map(f64::from)).collect();
        let v = mesh.positions.len();
        (op, Tensor::from_vec(img, (n, 4), &Device::Cpu).unwrap(), Tensor::from_vec(pos, (v, 3), &Device::Cpu).unwrap())
    }

    fn camera(eye: Vec3, res: usize) -> Camera {
        Camera::look_at(eye, Vec3::ZERO, Vec3::Z, 0.9, res, res)
    }

    #[test]
    fn gradients_match_finite_differences() -> anyhow::Result<()> {
        let mesh = blob();
        for eye in [Vec3::new(0.3, -3.5, 1.2), Vec3::new(2.5, 2.0, -1.0)] {
            let cam = camera(eye, 20);
            let (op, img, pos) = setup(&mesh, &cam);
            let report = check_gradient_with(
                |x| antialias(op.clone(), &x[0], &x[1]),
                &[img, pos],
                &GradCheckOptions { eps: 1e-7, tol: 1e-4, ..Default::default() },
            )?;
            println!("{report}");
        }
        Ok(())
    }

    #[test]
    fn coverage_follows_the_outline() -> anyhow::Result<()> {
        // A big square at depth 3 whose left edge is at x = 0.3 pixels right of a pixel boundary:
        // along each row, the antialiased coverage of the two pixels beside the edge must add up
        // to the exact covered length across them.
        let mut b = MeshBuilder::new();
        let part = b.part(PartMaterial { name: "m".into(), base_color: BaseColor::Constant(Vec3::splat(0.5)), roughness: Scalar::Constant(0.5), metallic: Scalar::Constant(0.0) });
        let _ = part;
        let mut mesh = b.build();
        let cam = Camera::look_at(Vec3::new(0.0, 0.0, 3.0), Vec3::ZERO, Vec3::Y, 0.8, 16, 16);
        let f = cam.focal() as f64;
        // World x of the pixel column boundary 8 (image centre) + 0.3 px, at depth 3.
        let edge_x = (0.3 / f * 3.0) as f32;
        mesh.positions = vec![Vec3::new(edge_x, -5.0, 0.0), Vec3::new(5.0, -5.0, 0.0), Vec3::new(5.0, 5.0, 0.0), Vec3::new(edge_x, 5.0, 0.0)];
        mesh.normals = vec![Vec3::Z; 4];
        mesh.uvs = vec![glam::Vec2::ZERO; 4];
        mesh.triangles = vec![[0, 1, 2], [0, 2, 3]];
        mesh.triangle_part = vec![0, 0];
        let (op, img, pos) = setup(&mesh, &cam);
        let out = antialias(op, &img, &pos)?.to_vec2::<f64>()?;
        for y in 2..14 {
            let a = |x: usize| out[y * 16 + x][3];
            // Pixel 7 spans [7, 8], pixel 8 spans [8, 9]: the edge at 8.3 covers 0.7 of pixel 8.
            assert!((a(7) - 0.0).abs() < 1e-6 && (a(8) - 0.7).abs() < 1e-4, "row {y}: {} {}", a(7), a(8));
        }
        Ok(())
    }
}
