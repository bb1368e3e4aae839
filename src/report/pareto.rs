//! The Pareto front of (cost, quality) points: the points no other point beats on both (lower or
//! equal cost and higher or equal quality, one of them strictly).

/// Indices of the front, sorted by increasing cost (minimise x, maximise y). Points with a NaN
/// coordinate are never on it; of exact duplicates only the first is kept.
pub fn pareto_front(points: &[(f64, f64)]) -> Vec<usize> {
    let mut order: Vec<usize> = (0..points.len()).filter(|&i| !points[i].0.is_nan() && !points[i].1.is_nan()).collect();
    // By cost, then best quality first, then index (stable for duplicates).
    order.sort_by(|&a, &b| points[a].0.total_cmp(&points[b].0).then(points[b].1.total_cmp(&points[a].1)).then(a.cmp(&b)));
    let mut front = Vec::new();
    let mut best = f64::NEG_INFINITY;
    for i in order {
        if points[i].1 > best {
            best = points[i].1;
            front.push(i);
        }
    }
    front
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn hand_worked_front() {
        // (time, PSNR): 0 and 2 and 4 are on the front; 1 is beaten by 0 (slower and worse), 3 by 2.
        let p = [(1.0, 20.0), (2.0, 19.0), (3.0, 25.0), (4.0, 24.0), (10.0, 26.0)];
        assert_eq!(pareto_front(&p), vec![0, 2, 4]);
        // Same cost: only the better one; exact duplicates: the first.
        assert_eq!(pareto_front(&[(1.0, 2.0), (1.0, 3.0), (1.0, 3.0)]), vec![1]);
        assert_eq!(pareto_front(&[(f64::NAN, 9.0), (1.0, 1.0)]), vec![1]);
        assert!(pareto_front(&[]).is_empty());
    }

    fn dominates(a: (f64, f64), b: (f64, f64)) -> bool {
        a.0 <= b.0 && a.1 >= b.1 && (a.0 < b.0 || a.1 > b.1)
    }

    proptest! {
        #[test]
        fn front_points_are_undominated_and_the_rest_dominated(pts in prop::collection::vec((0.0f64..10.0, 0.0f64..10.0), 1..40)) {
            let front = pareto_front(&pts);
            for &i in &front {
                prop_assert!(!pts.iter().any(|&q| dominates(q, pts[i])));
            }
            for (i, &p) in pts.iter().enumerate() {
                if !front.contains(&i) {
                    prop_assert!(pts.iter().enumerate().any(|(j, &q)| dominates(q, p) || (q == p && j < i)));
                }
            }
        }
    }
}
