//! Finite-difference checks of the tape's gradients.
//!
//! The loss is a fixed random projection `L = Σ rᵢ·outᵢ` of a layer's output; its gradient
//! with respect to sampled entries of every input and every parameter the layer read is
//! compared with the central difference `(L(θ + ε) − L(θ − ε)) / 2ε`, each side a fresh
//! forward on a fresh tape.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::{Tape, Var};
use crate::error::{PolicyError, Result};
use crate::weights::{Scope, Weights};

/// Settings of a finite-difference check.
#[derive(Debug, Clone, Copy)]
pub struct FdOptions {
    /// Step ε.
    pub eps: f32,
    /// Entries sampled per tensor.
    pub per_tensor: usize,
    /// Absolute tolerance.
    pub atol: f64,
    /// Relative tolerance.
    pub rtol: f64,
    /// Seed of the projection and of the sampled entries.
    pub seed: u64,
}

impl Default for FdOptions {
    fn default() -> Self {
        Self {
            eps: 1e-2,
            per_tensor: 6,
            atol: 2e-3,
            rtol: 2e-2,
            seed: 7,
        }
    }
}

/// The outcome of a check: the worst entry relative to its tolerance (≤ 1 passes).
#[derive(Debug, Clone)]
pub struct FdReport {
    /// Entries compared.
    pub checked: usize,
    /// Largest |analytic − numeric| / (atol + rtol·max(|analytic|, |numeric|)).
    pub worst_ratio: f64,
    /// Where the worst entry is (`input 0[12]`, `key[3]`) and its two values.
    pub worst: String,
    /// Tensors whose gradient was checked (inputs and parameter keys).
    pub tensors: Vec<String>,
}

impl FdReport {
    /// Whether every entry is within tolerance and something was checked.
    pub fn passed(&self) -> bool {
        self.checked > 0 && self.worst_ratio <= 1.0
    }
}

/// Checks the gradients of `build` (a layer on a tape, reading its parameters from the
/// scope `prefix` of `weights`, with `inputs` as variables).
pub fn finite_difference_check<F>(
    weights: &Weights,
    prefix: &str,
    inputs: &[(Vec<f32>, Vec<usize>)],
    opts: FdOptions,
    build: F,
) -> Result<FdReport>
where
    F: Fn(&mut Tape, &Scope<'_>, &[Var]) -> Result<Var>,
{
    let run = |w: &Weights, xs: &[(Vec<f32>, Vec<usize>)]| -> Result<(Tape, Vec<Var>, Var)> {
        let mut t = Tape::new();
        let vars = xs
            .iter()
            .map(|(v, s)| t.variable(v.clone(), s))
            .collect::<Result<Vec<_>>>()?;
        let out = build(&mut t, &w.scope(prefix), &vars)?;
        Ok((t, vars, out))
    };
    let (tape, vars, out) = run(weights, inputs)?;
    let mut rng = ChaCha8Rng::seed_from_u64(opts.seed);
    let r: Vec<f32> = (0..tape.value(out).len())
        .map(|_| rng.random_range(-1.0f32..1.0))
        .collect();
    let loss = |t: &Tape, o: Var| -> f64 {
        t.value(o)
            .iter()
            .zip(&r)
            .map(|(a, b)| f64::from(*a) * f64::from(*b))
            .sum()
    };
    let grads = tape.backward(out, &r)?;
    let mut report = FdReport {
        checked: 0,
        worst_ratio: 0.0,
        worst: String::new(),
        tensors: Vec::new(),
    };
    let compare = |report: &mut FdReport, name: String, analytic: f64, numeric: f64| {
        let ratio = (analytic - numeric).abs()
            / (opts.atol + opts.rtol * analytic.abs().max(numeric.abs()));
        report.checked += 1;
        if ratio > report.worst_ratio || !ratio.is_finite() {
            report.worst_ratio = if ratio.is_finite() {
                ratio
            } else {
                f64::INFINITY
            };
            report.worst = format!("{name}: analytic {analytic:.6e}, numeric {numeric:.6e}");
        }
    };
    let h = f64::from(opts.eps);
    for (i, v) in vars.iter().enumerate() {
        report.tensors.push(format!("input {i}"));
        let n = inputs[i].0.len();
        for _ in 0..opts.per_tensor.min(n) {
            let j = rng.random_range(0..n);
            let side = |sign: f32| -> Result<f64> {
                let mut xs = inputs.to_vec();
                xs[i].0[j] += sign * opts.eps;
                let (t, _, o) = run(weights, &xs)?;
                Ok(loss(&t, o))
            };
            let numeric = (side(1.0)? - side(-1.0)?) / (2.0 * h);
            let analytic = grads.of(*v).map_or(0.0, |g| f64::from(g[j]));
            compare(&mut report, format!("input {i}[{j}]"), analytic, numeric);
        }
    }
    for (key, v) in tape.params() {
        report.tensors.push(key.clone());
        let n = tape.value(*v).len();
        for _ in 0..opts.per_tensor.min(n) {
            let j = rng.random_range(0..n);
            let side = |sign: f32| -> Result<f64> {
                let mut w = weights.clone();
                w.f32_mut(key)?[j] += sign * opts.eps;
                let (t, _, o) = run(&w, inputs)?;
                Ok(loss(&t, o))
            };
            let numeric = (side(1.0)? - side(-1.0)?) / (2.0 * h);
            let analytic = grads.of(*v).map_or(0.0, |g| f64::from(g[j]));
            compare(&mut report, format!("{key}[{j}]"), analytic, numeric);
        }
    }
    if report.checked == 0 {
        return Err(PolicyError::NonFinite {
            what: "finite-difference check (no input or parameter to check)".into(),
        });
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_wrong_backward_pass_fails_the_check() {
        let w = Weights::from_tensors("none", Default::default());
        let x = (vec![0.3f32, -0.7, 1.1], vec![3]);
        let check = |factor: f32| {
            finite_difference_check(
                &w,
                "",
                std::slice::from_ref(&x),
                FdOptions::default(),
                |t, _, v| {
                    let a = v[0];
                    let y = t.value(a).iter().map(|x| x * x).collect();
                    Ok(t.push(
                        y,
                        vec![3],
                        &[a],
                        Some(Box::new(move |vals, g, gr| {
                            let d: Vec<f32> = vals
                                .get(a)
                                .iter()
                                .zip(g)
                                .map(|(x, g)| factor * x * g)
                                .collect();
                            gr.add(a, &d);
                        })),
                    ))
                },
            )
            .unwrap()
        };
        assert!(check(2.0).passed(), "d(x²) = 2x");
        let wrong = check(1.9);
        assert!(!wrong.passed(), "a 5 % error is caught: {wrong:?}");
    }
}
