//! Another library's ray queries measured against our `Bvh` on the same rays: first whether they
//! return the same hits (a library that disagrees does not count), then single-thread rays per CPU
//! second with ours taking turns in every round, as ratios to ours.

use glam::Vec3;
use reconstruct::geometry::bvh::Bvh;

/// Relative tolerance on t for two hits to agree (float orderings of the same test may differ in
/// the last bits; a different surface differs by far more).
const T_TOLERANCE: f32 = 1e-5;

/// Rays per CPU second of `queries` queries taking turns over `rays` (bench_rays' `cpu_rates`).
pub type CpuRates<'a> = &'a dyn Fn(&[(Vec3, Vec3)], usize, &dyn Fn(usize, Vec3, Vec3) -> bool) -> Vec<Option<f64>>;

/// One structure of another library: its closest hit (mesh triangle index, t) and, where the
/// library exposes it, its occlusion query, both for t in [0, ∞).
pub struct Alternative<'a> {
    pub name: String,
    pub closest: Box<dyn Fn(Vec3, Vec3) -> Option<(u32, f32)> + 'a>,
    pub any_hit: Option<Box<dyn Fn(Vec3, Vec3) -> bool + 'a>>,
}

/// Hit agreement between our `Bvh` and an alternative over a set of rays.
#[derive(Default)]
struct Agreement {
    rays: usize,
    agree: usize,
    /// We hit, they missed.
    only_ours: usize,
    /// They hit, we missed.
    only_theirs: usize,
    /// Both hit another triangle at the same t (a ray through a shared edge or vertex).
    tie: usize,
    /// Both hit, at another t.
    differ: usize,
    /// Occlusion answers that differ from ours.
    any_differ: Option<usize>,
    examples: Vec<String>,
}

fn agreement(ours: &Bvh, alt: &Alternative, rays: &[(Vec3, Vec3)]) -> Agreement {
    let mut a = Agreement { rays: rays.len(), ..Default::default() };
    for (i, &(o, d)) in rays.iter().enumerate() {
        let mine = ours.closest_hit(o, d, 0.0, f32::INFINITY).map(|h| (h.triangle, h.t));
        let theirs = (alt.closest)(o, d);
        let close = |s: f32, t: f32| (s - t).abs() <= T_TOLERANCE * s.abs().max(t.abs());
        let kind = match (mine, theirs) {
            (None, None) => None,
            (Some((ta, sa)), Some((tb, sb))) if ta == tb && close(sa, sb) => None,
            (Some(_), None) => Some(&mut a.only_ours),
            (None, Some(_)) => Some(&mut a.only_theirs),
            (Some((_, sa)), Some((_, sb))) if close(sa, sb) => Some(&mut a.tie),
            _ => Some(&mut a.differ),
        };
        match kind {
            None => a.agree += 1,
            Some(count) => {
                *count += 1;
                if a.examples.len() < 5 {
                    a.examples.push(format!("ray {i}: o {o:?} d {d:?}: ours {mine:?}, theirs {theirs:?}"));
                }
            }
        }
        if let Some(any) = &alt.any_hit {
            let differs = any(o, d) != ours.any_hit(o, d, 0.0, f32::INFINITY);
            *a.any_differ.get_or_insert(0) += differs as usize;
        }
    }
    a
}

/// Print the agreement of every alternative with `ours` on both ray sets (mismatching rays, the
/// first few per structure, to stderr), then their single-thread rates beside ours.
pub fn report(ours: &Bvh, alternatives: &[Alternative], coherent: &[(Vec3, Vec3)], incoherent: &[(Vec3, Vec3)], cpu_rates: CpuRates) {
    println!("\nHit agreement with `Bvh` (medium preset; same triangle and t within {T_TOLERANCE:e} relative, or both miss):\n");
    println!("| structure | rays | count | agree | only ours hit | only theirs hit | other triangle, same t | other t | any-hit answers differing |");
    println!("|---|---|---|---|---|---|---|---|---|");
    for alt in alternatives {
        for (set, rays) in [("coherent", coherent), ("incoherent", incoherent)] {
            let a = agreement(ours, alt, rays);
            let any = a.any_differ.map_or("n/a".into(), |n| n.to_string());
            println!(
                "| {} | {set} | {} | {} | {} | {} | {} | {} | {any} |",
                alt.name, a.rays, a.agree, a.only_ours, a.only_theirs, a.tie, a.differ
            );
            for e in &a.examples {
                eprintln!("  {}, {set}: {e}", alt.name);
            }
        }
    }

    // Query 0 is ours, k > 0 the alternative k − 1; all take turns in every round.
    let closest = |k: usize, o: Vec3, d: Vec3| match k {
        0 => ours.closest_hit(o, d, 0.0, f32::INFINITY).is_some(),
        _ => (alternatives[k - 1].closest)(o, d).is_some(),
    };
    let occluders: Vec<&dyn Fn(Vec3, Vec3) -> bool> = alternatives.iter().filter_map(|a| a.any_hit.as_deref()).collect();
    let occluded = |k: usize, o: Vec3, d: Vec3| match k {
        0 => ours.any_hit(o, d, 0.0, f32::INFINITY),
        _ => occluders[k - 1](o, d),
    };
    let n = alternatives.len() + 1;
    let coh = cpu_rates(coherent, n, &closest);
    let inc = cpu_rates(incoherent, n, &closest);
    let any = cpu_rates(incoherent, occluders.len() + 1, &occluded);

    println!("\nOne thread, rays per CPU second (Mray/s), taking turns with ours; ratio = rate / ours in the same run:\n");
    println!("| structure | coherent closest | ratio | incoherent closest | ratio | incoherent any-hit | ratio |");
    println!("|---|---|---|---|---|---|---|");
    let fmt = |r: Option<f64>| r.map_or("n/a".into(), |r| format!("{r:.2}"));
    let ratio = |r: Option<f64>, base: Option<f64>| match (r, base) {
        (Some(r), Some(b)) if b > 0.0 => format!("{:.2}", r / b),
        _ => "n/a".into(),
    };
    println!(
        "| CWBVH (Bvh), {} node test, medium | {} | 1.00 | {} | 1.00 | {} | 1.00 |",
        ours.node_test().name(),
        fmt(coh[0]),
        fmt(inc[0]),
        fmt(any[0])
    );
    let mut next_occluder = 1;
    for (k, alt) in alternatives.iter().enumerate() {
        let (a, r) = if alt.any_hit.is_some() {
            next_occluder += 1;
            (fmt(any[next_occluder - 1]), ratio(any[next_occluder - 1], any[0]))
        } else {
            ("n/a (not exposed)".into(), "".into())
        };
        println!(
            "| {} | {} | {} | {} | {} | {a} | {r} |",
            alt.name,
            fmt(coh[k + 1]),
            ratio(coh[k + 1], coh[0]),
            fmt(inc[k + 1]),
            ratio(inc[k + 1], inc[0])
        );
    }
}

/// Build rounds per structure for [`build_ms`]; the fastest counts.
const BUILD_ROUNDS: usize = 3;

/// Fastest of [`BUILD_ROUNDS`] wall-clock runs of `build`, in ms (obvhs, tinybvh and Embree all
/// build on every thread, so this is wall time, not one thread's CPU time).
pub fn build_ms(build: &dyn Fn()) -> f64 {
    (0..BUILD_ROUNDS)
        .map(|_| {
            let t = std::time::Instant::now();
            build();
            t.elapsed().as_secs_f64() * 1e3
        })
        .fold(f64::INFINITY, f64::min)
}
