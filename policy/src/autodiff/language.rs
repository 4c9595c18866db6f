//! Taped twin of the instruction encoder ([`crate::language::InstructionEncoder`]): the
//! token projection, the learned readout token in front, sin/cos positions and the pre-norm
//! Transformer layers, returning output token 0 (the FiLM condition).

use super::layers::{layer_norm, linear};
use super::{Act, Tape, Var};
use crate::error::{PolicyError, Result};
use crate::language::positional_encoding;
use crate::layers::rows_of;
use crate::weights::Scope;

/// The FiLM condition `[1, dim]` of `tokens` `[T, token_dim]` (data, no gradient), reading
/// `instruction_embedding`, `readout` and `scene_instruction_encoder.layers.*` from `s`.
pub fn instruction_condition(
    t: &mut Tape,
    s: &Scope<'_>,
    tokens: &[f32],
    heads: usize,
    dim_head: usize,
) -> Result<Var> {
    let token_dim = s.sub("instruction_embedding").shape("weight", 2)?[1];
    let n = rows_of("instruction tokens", tokens.len(), token_dim)?;
    let x = t.constant(tokens.to_vec(), &[n, token_dim])?;
    instruction_condition_var(t, s, x, heads, dim_head)
}

/// As [`instruction_condition`] with the tokens `[T, token_dim]` a taped value (so their
/// gradient is available, e.g. to check it).
pub fn instruction_condition_var(
    t: &mut Tape,
    s: &Scope<'_>,
    tokens: Var,
    heads: usize,
    dim_head: usize,
) -> Result<Var> {
    let embed = s.sub("instruction_embedding");
    // `shape` checked the rank, so both axes exist.
    let ws = embed.shape("weight", 2)?;
    let (dim, token_dim) = (ws[0], ws[1]);
    let n_tok = rows_of("instruction tokens", t.value(tokens).len(), token_dim)?;
    let readout = t.param(s, "readout", &[1, 1, dim])?;
    // The readout row goes in front: rows are contiguous, so a row concatenation is a
    // concatenation of the flat buffers.
    let x = if n_tok == 0 {
        t.reshape(readout, &[1, dim])?
    } else {
        let proj = linear(t, &embed, tokens, dim, token_dim, true)?;
        let r = t.reshape(readout, &[1, dim])?;
        let p = t.reshape(proj, &[1, n_tok * dim])?;
        let cat = t.concat_cols(r, dim, p, n_tok * dim)?;
        t.reshape(cat, &[n_tok + 1, dim])?
    };
    let n = n_tok + 1;
    let pe = t.constant(positional_encoding(n, dim), &[n, dim])?;
    let mut x = t.add(x, pe)?;
    let layers = s.sub("scene_instruction_encoder").sub("layers");
    let inner = heads * dim_head;
    let mut depth = 0;
    while layers.contains(&format!("{depth}.0.norm.weight")) {
        let l = layers.sub(&depth.to_string());
        let a = l.sub("0");
        let f = l.sub("1").sub("net");
        // Attention, residual.
        let h = layer_norm(t, &a.sub("norm"), x, dim)?;
        let qkv = linear(t, &a.sub("to_qkv"), h, 3 * inner, dim, false)?;
        let o = t.self_attention(qkv, n, heads, dim_head)?;
        let o = linear(t, &a.sub("to_out"), o, dim, inner, false)?;
        x = t.add(x, o)?;
        // Feed-forward, residual.
        let hidden = f.sub("1").shape("weight", 2)?[0];
        let h = layer_norm(t, &f.sub("0"), x, dim)?;
        let h = linear(t, &f.sub("1"), h, hidden, dim, true)?;
        let h = t.act(h, Act::Gelu);
        let h = linear(t, &f.sub("3"), h, dim, hidden, true)?;
        x = t.add(x, h)?;
        depth += 1;
    }
    if depth == 0 {
        return Err(PolicyError::MissingTensor {
            name: layers.key("0.0.norm.weight"),
            file: "instruction encoder weights".into(),
        });
    }
    t.gather_rows(x, dim, &[0])
}

impl Tape {
    /// Multi-head softmax self-attention over `n` tokens: `qkv` `[n, 3·heads·dim_head]` (q, k,
    /// v blocks, heads contiguous within each) to `[n, heads·dim_head]`, with scores
    /// `q·k / √dim_head`. Scores and softmax run in f64 as
    /// [`crate::language::InstructionEncoder`]'s attention; the weights are kept for the
    /// backward pass.
    pub fn self_attention(
        &mut self,
        qkv: Var,
        n: usize,
        heads: usize,
        dim_head: usize,
    ) -> Result<Var> {
        let inner = heads * dim_head;
        if inner == 0 || self.value(qkv).len() != n * 3 * inner {
            return Err(PolicyError::ShapeMismatch {
                name: "self-attention q, k, v".into(),
                expected: vec![n, 3 * inner],
                got: self.shape(qkv).to_vec(),
            });
        }
        let scale = 1.0 / (dim_head as f64).sqrt();
        let at =
            move |i: usize, part: usize, hd: usize| i * 3 * inner + part * inner + hd * dim_head;
        let v = self.value(qkv);
        // probs[(hd·n + i)·n + j]: the weight of token j in token i's output, head hd.
        let mut probs = vec![0.0f32; heads * n * n];
        let mut o = vec![0.0f32; n * inner];
        let mut w = vec![0.0f64; n];
        for hd in 0..heads {
            for i in 0..n {
                let q = &v[at(i, 0, hd)..at(i, 0, hd) + dim_head];
                let mut max = f64::NEG_INFINITY;
                for (j, wj) in w.iter_mut().enumerate() {
                    let k = &v[at(j, 1, hd)..at(j, 1, hd) + dim_head];
                    let s = q
                        .iter()
                        .zip(k)
                        .map(|(a, b)| f64::from(*a) * f64::from(*b))
                        .sum::<f64>()
                        * scale;
                    *wj = s;
                    max = max.max(s);
                }
                let mut sum = 0.0;
                for wj in w.iter_mut() {
                    *wj = (*wj - max).exp();
                    sum += *wj;
                }
                let oi = &mut o[i * inner + hd * dim_head..i * inner + (hd + 1) * dim_head];
                for (j, wj) in w.iter().enumerate() {
                    let a = (wj / sum) as f32;
                    probs[(hd * n + i) * n + j] = a;
                    let vj = &v[at(j, 2, hd)..at(j, 2, hd) + dim_head];
                    for (oc, vc) in oi.iter_mut().zip(vj) {
                        *oc += a * vc;
                    }
                }
            }
        }
        Ok(self.push(
            o,
            vec![n, inner],
            &[qkv],
            Some(Box::new(move |vals, g, gr| {
                let v = vals.get(qkv);
                let Some(acc) = gr.acc(qkv) else {
                    return;
                };
                let mut dp = vec![0.0f64; n];
                for hd in 0..heads {
                    for i in 0..n {
                        let gi = &g[i * inner + hd * dim_head..i * inner + (hd + 1) * dim_head];
                        let p = &probs[(hd * n + i) * n..(hd * n + i + 1) * n];
                        // dP[j] = gᵢ·vⱼ; dV[j] += P[j]·gᵢ.
                        for (j, dpj) in dp.iter_mut().enumerate() {
                            let vj = &v[at(j, 2, hd)..at(j, 2, hd) + dim_head];
                            *dpj = gi
                                .iter()
                                .zip(vj)
                                .map(|(a, b)| f64::from(*a) * f64::from(*b))
                                .sum();
                            for (a, gc) in acc[at(j, 2, hd)..at(j, 2, hd) + dim_head]
                                .iter_mut()
                                .zip(gi)
                            {
                                *a += p[j] * gc;
                            }
                        }
                        // Softmax: dS[j] = P[j]·(dP[j] − Σ P·dP), then through q·k·scale.
                        let mean: f64 = p.iter().zip(&dp).map(|(a, b)| f64::from(*a) * b).sum();
                        for j in 0..n {
                            let ds = f64::from(p[j]) * (dp[j] - mean) * scale;
                            for c in 0..dim_head {
                                let qc = f64::from(v[at(i, 0, hd) + c]);
                                let kc = f64::from(v[at(j, 1, hd) + c]);
                                acc[at(i, 0, hd) + c] += (ds * kc) as f32;
                                acc[at(j, 1, hd) + c] += (ds * qc) as f32;
                            }
                        }
                    }
                }
            })),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::autodiff::check::{finite_difference_check, FdOptions};
    use crate::autodiff::layers::tests::random;
    use crate::autodiff::layers::tests::small_weights;
    use crate::language::InstructionEncoder;

    // small_weights: film_dim 16, token_dim 12, one layer, 2 heads of 4.
    const HEADS: usize = 2;
    const DIM_HEAD: usize = 4;
    const TOKEN_DIM: usize = 12;

    #[test]
    fn instruction_condition_matches_inference_and_finite_differences() {
        let w = small_weights();
        let s = w.scope("");
        let tokens = random(3 * TOKEN_DIM, 11);
        let enc = InstructionEncoder::load(&s, HEADS, DIM_HEAD).unwrap();
        let want = enc.condition(&tokens, 1).unwrap();
        let mut t = Tape::new();
        let y = instruction_condition(&mut t, &s, &tokens, HEADS, DIM_HEAD).unwrap();
        assert_eq!(t.shape(y), &[1, enc.dim]);
        // Both paths accumulate dense products differently (f64 dot against f32 GEMM).
        for (i, (a, b)) in t.value(y).iter().zip(&want).enumerate() {
            assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()), "[{i}]: {a} vs {b}");
        }
        let r = finite_difference_check(
            &w,
            "",
            &[(tokens, vec![3, TOKEN_DIM])],
            FdOptions::default(),
            |t, s, v| instruction_condition_var(t, s, v[0], HEADS, DIM_HEAD),
        )
        .unwrap();
        assert!(
            r.passed(),
            "worst {:.3} at {} ({:?})",
            r.worst_ratio,
            r.worst,
            r.tensors
        );
        // Tokens, embedding weight and bias, readout, and the layer's 10 tensors.
        assert_eq!(r.tensors.len(), 14, "{:?}", r.tensors);
    }

    #[test]
    fn self_attention_passes_finite_differences() {
        let w = small_weights();
        let (n, heads, dh) = (4, 3, 2);
        // Larger scores than the encoder's, so the softmax is far from uniform.
        let qkv: Vec<f32> = random(n * 3 * heads * dh, 12)
            .iter()
            .map(|v| 2.0 * v)
            .collect();
        let r = finite_difference_check(
            &w,
            "",
            &[(qkv, vec![n, 3 * heads * dh])],
            FdOptions {
                per_tensor: 24,
                ..FdOptions::default()
            },
            |t, _, v| t.self_attention(v[0], n, heads, dh),
        )
        .unwrap();
        assert!(r.passed(), "worst {:.3} at {}", r.worst_ratio, r.worst);
    }

    #[test]
    fn bad_instruction_shapes_are_errors() {
        let w = small_weights();
        let s = w.scope("");
        let mut t = Tape::new();
        assert!(instruction_condition(&mut t, &s, &[0.0; 5], HEADS, DIM_HEAD).is_err());
        assert!(instruction_condition(&mut t, &s, &[0.0; 12], 3, DIM_HEAD).is_err());
        let empty = w.scope("nothing.");
        assert!(instruction_condition(&mut t, &empty, &[0.0; 12], HEADS, DIM_HEAD).is_err());
        let x = t.variable(vec![0.0; 10], &[10]).unwrap();
        assert!(t.self_attention(x, 2, 1, 2).is_err());
    }
}
