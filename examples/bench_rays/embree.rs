//! Intel Embree 3 (through the `embree3` crate, behind this package's off-by-default `embree`
//! feature; needs the system library, Debian `libembree-dev`) on bench_rays' rays, side by side
//! with our `Bvh` ([`super::side_by_side`]): one triangle geometry holding the mesh, scenes built at
//! Embree's default (medium) and high (spatial splits) quality, single-ray `rtcIntersect1` and
//! `rtcOccluded1` with an incoherent context.

use embree3::{BufferUsage, BuildQuality, Device, Format, GeometryKind, IntersectContext, Ray, RayHit, Scene};
use glam::Vec3;
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::Mesh;

use super::side_by_side::{build_ms, report, Alternative, CpuRates};

/// A committed scene over `mesh` at `quality`; its primitive ids are the mesh's triangle indices.
fn scene<'a>(device: &Device, mesh: &Mesh, quality: BuildQuality) -> Result<Scene<'a>, String> {
    let mut geometry = device.create_geometry(GeometryKind::TRIANGLE).map_err(|e| format!("geometry: {e:?}"))?;
    let vertices: Vec<[f32; 3]> = mesh.positions.iter().map(|p| p.to_array()).collect();
    geometry
        .set_new_buffer::<[f32; 3]>(BufferUsage::VERTEX, 0, Format::FLOAT3, 12, vertices.len())
        .map_err(|e| format!("vertex buffer: {e:?}"))?
        .copy_from_slice(&vertices);
    geometry
        .set_new_buffer::<[u32; 3]>(BufferUsage::INDEX, 0, Format::UINT3, 12, mesh.triangles.len())
        .map_err(|e| format!("index buffer: {e:?}"))?
        .copy_from_slice(&mesh.triangles);
    geometry.set_build_quality(quality);
    let geometry = geometry.commit();
    let mut scene = device.create_scene().map_err(|e| format!("scene: {e:?}"))?;
    scene.set_build_quality(quality);
    scene.attach_geometry(&geometry);
    scene.commit();
    Ok(scene)
}

fn closest(scene: &Scene, o: Vec3, d: Vec3) -> Option<(u32, f32)> {
    let mut ctx = IntersectContext::incoherent();
    let mut hit = RayHit::from(Ray::segment(o.to_array(), d.to_array(), 0.0, f32::INFINITY));
    scene.intersect(&mut ctx, &mut hit);
    hit.hit.is_valid().then_some((hit.hit.primID, hit.ray.tfar))
}

fn occluded(scene: &Scene, o: Vec3, d: Vec3) -> bool {
    let mut ctx = IntersectContext::incoherent();
    scene.occluded(&mut ctx, &mut Ray::segment(o.to_array(), d.to_array(), 0.0, f32::INFINITY))
}

fn alternative<'a>(name: &str, scene: &'a Scene) -> Alternative<'a> {
    Alternative {
        name: name.into(),
        closest: Box::new(move |o, d| closest(scene, o, d)),
        any_hit: Some(Box::new(move |o, d| occluded(scene, o, d))),
    }
}

/// Build Embree scenes over `mesh` and print their build times, hit agreement with `ours` and
/// rates beside ours.
pub fn compare(mesh: &Mesh, ours: &Bvh, coherent: &[(Vec3, Vec3)], incoherent: &[(Vec3, Vec3)], cpu_rates: CpuRates) {
    println!("\n## Embree 3 (embree3 crate 0.4.1, system libembree3) against `Bvh` on the same rays\n");
    let device = match Device::new() {
        Ok(d) => d,
        Err(e) => {
            println!("Embree device failed: {e:?}");
            return;
        }
    };
    println!("| structure | build ms (wall, all threads, fastest of 3) |");
    println!("|---|---|");
    println!("| CWBVH (Bvh), medium preset | {:.1} |", build_ms(&|| drop(std::hint::black_box(Bvh::build(mesh)))));
    for (name, quality) in [("medium", BuildQuality::MEDIUM), ("high", BuildQuality::HIGH)] {
        println!("| Embree scene, {name} quality | {:.1} |", build_ms(&|| drop(std::hint::black_box(scene(&device, mesh, quality)))));
    }
    let (medium, high) = match (scene(&device, mesh, BuildQuality::MEDIUM), scene(&device, mesh, BuildQuality::HIGH)) {
        (Ok(m), Ok(h)) => (m, h),
        (Err(e), _) | (_, Err(e)) => {
            println!("Embree scene failed: {e}");
            return;
        }
    };
    let alternatives = [alternative("Embree, medium quality", &medium), alternative("Embree, high quality", &high)];
    report(ours, &alternatives, coherent, incoherent, cpu_rates);
}
