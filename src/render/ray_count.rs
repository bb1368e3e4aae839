//! Rays traced by a render or a training step, by kind: primary (camera rays of a G-buffer),
//! shadow (occlusion tests toward a light sample or a BSDF sample that ends at the environment)
//! and bounce (closest-hit rays that continue a path with interreflection). The renderers count
//! per pixel and sum, so counting costs nothing per ray; the benchmarks turn the counts into
//! rays per second.
//!
//! Besides the counts each call returns, every G-buffer trace and Monte Carlo shading adds its
//! total once to a process-wide tally ([`traced_so_far`]): a caller that only sees a training step
//! from outside (a benchmark timing `Fit::step`) reads the rays the step traced as the difference
//! of two tallies. One relaxed atomic add per render, not per ray.

use std::iter::Sum;
use std::ops::{Add, AddAssign, Sub};
use std::sync::atomic::{AtomicU64, Ordering};

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RayCount {
    /// Camera rays (one per G-buffer pixel).
    pub primary: u64,
    /// Any-hit occlusion rays.
    pub shadow: u64,
    /// Closest-hit rays that find the surface a path bounces off.
    pub bounce: u64,
}

impl RayCount {
    pub const ZERO: RayCount = RayCount { primary: 0, shadow: 0, bounce: 0 };

    pub const fn shadow(n: u64) -> RayCount {
        RayCount { primary: 0, shadow: n, bounce: 0 }
    }

    pub const fn bounce(n: u64) -> RayCount {
        RayCount { primary: 0, shadow: 0, bounce: n }
    }

    /// Rays after the primary ones (what a renderer traces per sample).
    pub fn secondary(&self) -> u64 {
        self.shadow + self.bounce
    }

    pub fn total(&self) -> u64 {
        self.primary + self.secondary()
    }

    /// Millions of secondary rays per second over `seconds`.
    pub fn secondary_mrays_per_s(&self, seconds: f64) -> f64 {
        self.secondary() as f64 / seconds.max(f64::MIN_POSITIVE) / 1e6
    }
}

impl Add for RayCount {
    type Output = RayCount;
    fn add(self, o: RayCount) -> RayCount {
        RayCount { primary: self.primary + o.primary, shadow: self.shadow + o.shadow, bounce: self.bounce + o.bounce }
    }
}

impl AddAssign for RayCount {
    fn add_assign(&mut self, o: RayCount) {
        *self = *self + o;
    }
}

/// Difference of two tallies (later − earlier); saturates so a reordered read cannot wrap.
impl Sub for RayCount {
    type Output = RayCount;
    fn sub(self, o: RayCount) -> RayCount {
        RayCount {
            primary: self.primary.saturating_sub(o.primary),
            shadow: self.shadow.saturating_sub(o.shadow),
            bounce: self.bounce.saturating_sub(o.bounce),
        }
    }
}

impl Sum for RayCount {
    fn sum<I: Iterator<Item = RayCount>>(iter: I) -> RayCount {
        iter.fold(RayCount::ZERO, Add::add)
    }
}

static TALLY: [AtomicU64; 3] = [AtomicU64::new(0), AtomicU64::new(0), AtomicU64::new(0)];

/// Adds one render's rays to the process-wide tally (called by the renderers, once per render).
pub fn record(count: RayCount) {
    for (t, n) in TALLY.iter().zip([count.primary, count.shadow, count.bounce]) {
        if n > 0 {
            t.fetch_add(n, Ordering::Relaxed);
        }
    }
}

/// All rays the renderers have traced in this process so far.
pub fn traced_so_far() -> RayCount {
    let [p, s, b] = TALLY.each_ref().map(|t| t.load(Ordering::Relaxed));
    RayCount { primary: p, shadow: s, bounce: b }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_add_and_the_tally_grows_by_what_is_recorded() {
        let a = RayCount { primary: 1, shadow: 2, bounce: 3 };
        let b = RayCount { primary: 10, shadow: 20, bounce: 30 };
        assert_eq!([a, b].into_iter().sum::<RayCount>(), RayCount { primary: 11, shadow: 22, bounce: 33 });
        assert_eq!((a + b).secondary(), 55);
        assert_eq!((a + b).total(), 66);
        assert_eq!(a - b, RayCount::ZERO);
        // Other tests may record concurrently: the tally grows by at least what we add.
        let before = traced_so_far();
        record(b);
        let grown = traced_so_far() - before;
        assert!(grown.primary >= 10 && grown.shadow >= 20 && grown.bounce >= 30, "{grown:?}");
    }
}
