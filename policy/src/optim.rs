//! AdamW over a [`Weights`] store, as the reference trains (lr 1e-4, weight decay 5e-4,
//! none on biases and norms), with its moments saved beside the weights for resuming, and
//! an optional warm-up and cosine decay of the rate (a function of the step alone, so a
//! resumed run follows the same rates as an uninterrupted one).

use std::collections::HashMap;
use std::path::Path;

use crate::error::{PolicyError, Result};
use crate::fixtures::{StoredTensor, TensorData};
use crate::weights::Weights;

/// AdamW settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AdamWConfig {
    /// Learning rate.
    pub lr: f32,
    /// First-moment decay.
    pub beta1: f32,
    /// Second-moment decay.
    pub beta2: f32,
    /// Denominator guard.
    pub eps: f32,
    /// Decoupled weight decay of matrices (not of biases, norms or the radial basis).
    pub weight_decay: f32,
    /// How the rate changes with the step (`lr` is its peak).
    pub schedule: LrSchedule,
    /// Factor of the rate for the instruction's path into the field ([`conditions`]: the
    /// instruction encoder and the FiLM projections); 1 trains every parameter alike.
    pub conditioning_lr_scale: f32,
}

/// The learning rate as a function of the optimiser step.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum LrSchedule {
    /// `lr` at every step (the reference's training).
    Constant,
    /// Linear warm-up from 0 over `warmup` steps, then a cosine decay to 0 at step `total`
    /// (and 0 after it). Meant for fine-tuning trained weights with a fresh optimiser:
    /// the warm-up lets the second moments settle before full-size steps, and the decay
    /// anneals the weights instead of leaving them at a constant rate's noise level.
    Cosine {
        /// Steps of linear warm-up.
        warmup: u64,
        /// The step at which the rate reaches 0.
        total: u64,
    },
}

impl LrSchedule {
    /// The factor of the peak rate for update number `step + 1` (`step` updates done).
    pub fn factor(&self, step: u64) -> f64 {
        match *self {
            Self::Constant => 1.0,
            Self::Cosine { warmup, total } => {
                let s = step as f64 + 1.0;
                if s <= warmup as f64 {
                    s / (warmup as f64 + 1.0)
                } else if step >= total {
                    0.0
                } else {
                    let span = (total - warmup.min(total)).max(1) as f64;
                    let done = (s - warmup as f64 - 1.0) / span;
                    0.5 * (1.0 + (std::f64::consts::PI * done).cos())
                }
            }
        }
    }
}

impl AdamWConfig {
    /// The reference's settings (physical-robot training).
    pub fn reference() -> Self {
        Self {
            lr: 1e-4,
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
            weight_decay: 5e-4,
            schedule: LrSchedule::Constant,
            conditioning_lr_scale: 1.0,
        }
    }
}

/// Whether a parameter carries the instruction into the field: the instruction encoder
/// (`instruction_embedding`, `readout`, `scene_instruction_encoder`) and every FiLM
/// projection (`….film.…`).
pub fn conditions(key: &str) -> bool {
    [
        "instruction_embedding.",
        "readout",
        "scene_instruction_encoder.",
    ]
    .iter()
    .any(|p| key.starts_with(p))
        || key.contains(".film.")
}

/// Whether a parameter is weight-decayed: matrices yes; biases, norm affines and the radial
/// basis's means and widths no (the reference's grouping).
pub fn decays(key: &str, shape: &[usize]) -> bool {
    shape.len() >= 2
        && !key.ends_with("bias")
        && !key.contains("norm")
        && !key.contains("distance_expansion")
}

/// AdamW state: step count and the two moments of every parameter it has updated.
#[derive(Debug, Clone)]
pub struct AdamW {
    /// Settings.
    pub cfg: AdamWConfig,
    /// Updates applied so far.
    pub step: u64,
    moments: HashMap<String, (Vec<f32>, Vec<f32>)>,
}

impl AdamW {
    /// A fresh optimiser.
    pub fn new(cfg: AdamWConfig) -> Self {
        Self {
            cfg,
            step: 0,
            moments: HashMap::new(),
        }
    }

    /// Applies one update with `grads` (full key → gradient, same length as the weight).
    /// Every gradient is checked first: a non-finite or misshapen one changes nothing.
    pub fn update(&mut self, weights: &mut Weights, grads: &[(String, Vec<f32>)]) -> Result<()> {
        for (key, g) in grads {
            let (shape, w) = weights.f32_any(key)?;
            if w.len() != g.len() {
                return Err(PolicyError::ShapeMismatch {
                    name: format!("gradient of {key}"),
                    expected: shape,
                    got: vec![g.len()],
                });
            }
            if g.iter().any(|v| !v.is_finite()) {
                return Err(PolicyError::NonFinite {
                    what: format!("gradient of {key} (no parameter was updated)"),
                });
            }
        }
        let c = self.cfg;
        let lr = f64::from(c.lr) * c.schedule.factor(self.step);
        self.step += 1;
        let t = self.step as i32;
        let bc1 = 1.0 - f64::from(c.beta1).powi(t);
        let bc2 = 1.0 - f64::from(c.beta2).powi(t);
        let base_lr = lr;
        for (key, g) in grads {
            let lr = if conditions(key) {
                base_lr * f64::from(c.conditioning_lr_scale)
            } else {
                base_lr
            };
            let shape = weights.shape_of(key)?;
            let decay = if decays(key, &shape) {
                (lr * f64::from(c.weight_decay)) as f32
            } else {
                0.0
            };
            let w = weights.f32_mut(key)?;
            let (m, v) = self
                .moments
                .entry(key.clone())
                .or_insert_with(|| (vec![0.0; g.len()], vec![0.0; g.len()]));
            for i in 0..g.len() {
                m[i] = c.beta1 * m[i] + (1.0 - c.beta1) * g[i];
                v[i] = c.beta2 * v[i] + (1.0 - c.beta2) * g[i] * g[i];
                let mh = f64::from(m[i]) / bc1;
                let vh = f64::from(v[i]) / bc2;
                w[i] -= decay * w[i];
                w[i] -= (lr * mh / (vh.sqrt() + f64::from(c.eps))) as f32;
            }
        }
        Ok(())
    }

    /// Writes the moments and the step to a safetensors file (`m.<key>`, `v.<key>`,
    /// `step`).
    pub fn save(&self, path: &Path) -> Result<()> {
        let mut t = HashMap::new();
        for (k, (m, v)) in &self.moments {
            for (p, x) in [("m", m), ("v", v)] {
                t.insert(
                    format!("{p}.{k}"),
                    StoredTensor {
                        shape: vec![x.len()],
                        data: TensorData::F32(x.clone()),
                    },
                );
            }
        }
        t.insert(
            "step".into(),
            StoredTensor {
                shape: vec![1],
                data: TensorData::I64(vec![self.step as i64]),
            },
        );
        Weights::from_tensors("optimizer state", t).save(path)
    }

    /// Reads a state written by [`AdamW::save`]; every moment must match a parameter of
    /// `weights` in length.
    pub fn load(cfg: AdamWConfig, path: &Path, weights: &Weights) -> Result<Self> {
        let f = Weights::from_file(path)?;
        let step = match f.i64_any("step")? {
            (_, v) if v.len() == 1 && v[0] >= 0 => v[0] as u64,
            (shape, _) => {
                return Err(PolicyError::ShapeMismatch {
                    name: format!("step in {}", path.display()),
                    expected: vec![1],
                    got: shape,
                })
            }
        };
        let mut moments = HashMap::new();
        for key in f.keys() {
            let Some(k) = key.strip_prefix("m.") else {
                continue;
            };
            let (_, m) = f.f32_any(key)?;
            let (_, v) = f.f32_any(&format!("v.{k}"))?;
            let (shape, w) = weights.f32_any(k)?;
            if m.len() != w.len() || v.len() != w.len() {
                return Err(PolicyError::ShapeMismatch {
                    name: format!("optimizer moments of {k} in {}", path.display()),
                    expected: shape,
                    got: vec![m.len(), v.len()],
                });
            }
            moments.insert(k.to_string(), (m, v));
        }
        Ok(Self { cfg, step, moments })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn store(w: Vec<f32>, b: Vec<f32>) -> Weights {
        let mut t = HashMap::new();
        t.insert(
            "lin.weight".to_string(),
            StoredTensor {
                shape: vec![1, w.len()],
                data: TensorData::F32(w),
            },
        );
        t.insert(
            "lin.bias".to_string(),
            StoredTensor {
                shape: vec![b.len()],
                data: TensorData::F32(b),
            },
        );
        Weights::from_tensors("test", t)
    }

    #[test]
    fn adamw_minimises_a_quadratic_and_decays_only_matrices() {
        // L = ½|w − 3|² + ½|b + 1|²: the minimum is w = 3, b = −1.
        let mut w = store(vec![0.0, 1.0], vec![0.5]);
        let mut opt = AdamW::new(AdamWConfig {
            lr: 0.05,
            weight_decay: 0.0,
            ..AdamWConfig::reference()
        });
        for _ in 0..600 {
            let (_, wv) = w.f32_any("lin.weight").unwrap();
            let (_, bv) = w.f32_any("lin.bias").unwrap();
            let g = vec![
                (
                    "lin.weight".to_string(),
                    wv.iter().map(|x| x - 3.0).collect(),
                ),
                ("lin.bias".to_string(), bv.iter().map(|x| x + 1.0).collect()),
            ];
            opt.update(&mut w, &g).unwrap();
        }
        let (_, wv) = w.f32_any("lin.weight").unwrap();
        let (_, bv) = w.f32_any("lin.bias").unwrap();
        assert!(wv.iter().all(|x| (x - 3.0).abs() < 1e-2), "{wv:?}");
        assert!((bv[0] + 1.0).abs() < 1e-2, "{bv:?}");
        assert!(decays("a.weight", &[2, 3]) && !decays("a.bias", &[3]));
        assert!(!decays("x.norm_2.affine_weight", &[4, 3]));
        // With a zero gradient only the decay acts, and only on the matrix.
        let mut w = store(vec![1.0], vec![1.0]);
        let mut opt = AdamW::new(AdamWConfig {
            weight_decay: 0.5,
            lr: 0.1,
            ..AdamWConfig::reference()
        });
        let zero = vec![
            ("lin.weight".to_string(), vec![0.0]),
            ("lin.bias".to_string(), vec![0.0]),
        ];
        opt.update(&mut w, &zero).unwrap();
        assert!((w.f32_any("lin.weight").unwrap().1[0] - 0.95).abs() < 1e-6);
        assert_eq!(w.f32_any("lin.bias").unwrap().1[0], 1.0);
    }

    #[test]
    fn cosine_schedule_warms_up_decays_to_zero_and_scales_the_update() {
        let c = LrSchedule::Cosine {
            warmup: 4,
            total: 14,
        };
        let f: Vec<f64> = (0..16).map(|s| c.factor(s)).collect();
        // Warm-up: 1/5 .. 4/5, rising.
        for (k, v) in f[..4].iter().enumerate() {
            assert!((v - (k as f64 + 1.0) / 5.0).abs() < 1e-12, "{f:?}");
        }
        // Then the peak, falling monotonically to 0 at step `total` and staying there.
        assert!((f[4] - 1.0).abs() < 1e-12, "{f:?}");
        assert!(f[4..14].windows(2).all(|w| w[1] < w[0]), "{f:?}");
        assert!(
            (f[9] - 0.5).abs() < 1e-12,
            "halfway through the decay: {f:?}"
        );
        assert_eq!((f[14], f[15]), (0.0, 0.0));
        assert_eq!(LrSchedule::Constant.factor(1_000_000), 1.0);
        // The first AdamW step moves a parameter by about the scheduled rate.
        let mut w = store(vec![1.0], vec![0.0]);
        let mut opt = AdamW::new(AdamWConfig {
            lr: 0.1,
            weight_decay: 0.0,
            schedule: c,
            ..AdamWConfig::reference()
        });
        let g = vec![("lin.weight".to_string(), vec![1.0])];
        opt.update(&mut w, &g).unwrap();
        let moved = 1.0 - w.f32_any("lin.weight").unwrap().1[0];
        assert!((moved - 0.02).abs() < 1e-6, "{moved}");
    }

    #[test]
    fn the_conditioning_path_moves_at_its_own_rate() {
        let one = |v: f32| StoredTensor {
            shape: vec![1, 1],
            data: TensorData::F32(vec![v]),
        };
        let keys = [
            "scene_instruction_encoder.layers.0.0.to_qkv.weight",
            "readout",
            "down_blocks.0.block.transblock.ffn.so3_linear_1.film.weight",
            "down_blocks.0.block.transblock.ffn.so3_linear_1.weight",
            "trans_field_layer.weight",
        ];
        let mut w = Weights::from_tensors(
            "test",
            keys.iter().map(|k| (k.to_string(), one(1.0))).collect(),
        );
        let mut opt = AdamW::new(AdamWConfig {
            lr: 0.01,
            weight_decay: 0.0,
            conditioning_lr_scale: 10.0,
            ..AdamWConfig::reference()
        });
        let g: Vec<(String, Vec<f32>)> = keys.iter().map(|k| (k.to_string(), vec![1.0])).collect();
        opt.update(&mut w, &g).unwrap();
        let moved: Vec<f32> = keys
            .iter()
            .map(|k| 1.0 - w.f32_any(k).unwrap().1[0])
            .collect();
        // Adam's first step moves each parameter by about its rate.
        for (k, m) in keys.iter().zip(&moved) {
            let want = if conditions(k) { 0.1 } else { 0.01 };
            assert!((m - want).abs() < 1e-5, "{k}: moved {m}, want {want}");
        }
        assert_eq!(keys.iter().filter(|k| conditions(k)).count(), 3);
    }

    #[test]
    fn bad_gradients_change_nothing_and_state_round_trips() {
        let mut w = store(vec![1.0, 2.0], vec![0.0]);
        let mut opt = AdamW::new(AdamWConfig::reference());
        let nan = vec![
            ("lin.bias".to_string(), vec![1.0]),
            ("lin.weight".to_string(), vec![f32::NAN, 0.0]),
        ];
        assert!(opt.update(&mut w, &nan).is_err());
        assert_eq!(opt.step, 0);
        assert_eq!(w.f32_any("lin.bias").unwrap().1, vec![0.0]);
        let short = vec![("lin.weight".to_string(), vec![1.0])];
        assert!(opt.update(&mut w, &short).is_err());
        let good = vec![("lin.weight".to_string(), vec![0.5, -0.5])];
        opt.update(&mut w, &good).unwrap();
        let dir = std::env::temp_dir().join(format!("equact_adamw_{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("opt.safetensors");
        opt.save(&path).unwrap();
        let back = AdamW::load(AdamWConfig::reference(), &path, &w).unwrap();
        assert_eq!(back.step, 1);
        assert_eq!(back.moments, opt.moments);
        let other = store(vec![1.0, 2.0, 3.0], vec![0.0]);
        assert!(AdamW::load(AdamWConfig::reference(), &path, &other).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
