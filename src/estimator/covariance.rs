//! Covariances kept usable, for every estimator: symmetric, bounded, positive definite. The bottom of
//! `estimator/`: it uses nothing of its siblings.

/// Keeps a covariance usable: symmetric, trace at most `max_trace`, diagonal at least `floor`, positive definite
/// (reset to `reset·I` when it is not, or is not finite).
pub(crate) fn condition<const N: usize>(
    p: nalgebra::SMatrix<f64, N, N>,
    max_trace: f64,
    floor: f64,
    reset: f64,
) -> nalgebra::SMatrix<f64, N, N> {
    let fresh = || nalgebra::SMatrix::<f64, N, N>::identity() * reset.min(max_trace / N as f64);
    if !p.iter().all(|v| v.is_finite()) {
        return fresh();
    }
    let mut p = (p + p.transpose()) * 0.5;
    let tr = p.trace();
    if tr > max_trace {
        p *= max_trace / tr;
    }
    // A floor well below any information the data can give keeps P strictly positive definite.
    for i in 0..N {
        if p[(i, i)] < floor {
            p[(i, i)] = floor;
        }
    }
    if positive_definite(&p) { p } else { fresh() }
}

/// Whether a symmetric, finite matrix is positive definite: for 2×2 (every update of both trackers) its leading
/// minors, which is what a Cholesky factorisation checks, without the factorisation.
fn positive_definite<const N: usize>(p: &nalgebra::SMatrix<f64, N, N>) -> bool {
    if N == 2 { p[(0, 0)] > 0.0 && p[(0, 0)] * p[(1, 1)] - p[(0, 1)] * p[(1, 0)] > 0.0 } else { p.cholesky().is_some() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn condition_symmetrises_bounds_and_resets() {
        let p = nalgebra::Matrix3::new(2.0, 1.0, 0.0, 0.5, 2.0, 0.0, 0.0, 0.0, 1e9);
        let q = condition(p, 100.0, 1e-10, 10.0);
        assert_eq!(q, q.transpose());
        assert!(q.trace() <= 100.0 + 1e-9);
        assert!(q.cholesky().is_some());
        let bad = nalgebra::Matrix3::new(1.0, 5.0, 0.0, 5.0, 1.0, 0.0, 0.0, 0.0, 1.0);
        assert!(condition(bad, 100.0, 1e-10, 10.0).cholesky().is_some());
        let nan = nalgebra::Matrix3::from_element(f64::NAN);
        assert!(condition(nan, 100.0, 1e-10, 10.0).iter().all(|v| v.is_finite()));
    }
}
