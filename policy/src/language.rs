//! The instruction encoder: token embeddings (`[tokens, token_dim]`: CLIP's 53 × 512 as the
//! reference uses, or all-MiniLM-L6-v2's tokens × 384) projected to the FiLM width, a
//! learned readout token in front, sin/cos positions, and a pre-norm Transformer; output
//! token 0 is the condition of every FiLM layer.
//!
//! Spec: `equact.md` ("Language") and the `language_encoder` sidecar. No padding mask (all
//! tokens attend to each other, as the reference), no final norm, exact erf GELU.

use crate::error::{PolicyError, Result};
use crate::layers::{gelu, rows_of, LayerNorm, Linear};
use crate::weights::Scope;

/// One pre-norm Transformer layer (attention then feed-forward, both residual).
#[derive(Debug, Clone)]
struct EncoderLayer {
    attn_norm: LayerNorm,
    to_qkv: Linear,
    to_out: Linear,
    ff_norm: LayerNorm,
    ff1: Linear,
    ff2: Linear,
}

/// The instruction encoder of `EquFieldUnet`.
#[derive(Debug, Clone)]
pub struct InstructionEncoder {
    /// Model width (the FiLM condition size).
    pub dim: usize,
    /// Attention heads.
    pub heads: usize,
    /// Width of one head.
    pub dim_head: usize,
    readout: Vec<f32>,
    embed: Linear,
    layers: Vec<EncoderLayer>,
}

/// The 1-D sin/cos positional encoding: pe[p, 2i] = sin(p·e^(−2i ln 10000 / d)),
/// pe[p, 2i+1] = cos(same); `[n, d]`, computed in f32 as the reference.
pub fn positional_encoding(n: usize, d: usize) -> Vec<f32> {
    let mut pe = vec![0.0f32; n * d];
    let scale = (-(10000.0f64).ln() / d as f64) as f32;
    for p in 0..n {
        for i in (0..d).step_by(2) {
            let div = (i as f32 * scale).exp();
            let a = p as f32 * div;
            pe[p * d + i] = a.sin();
            if i + 1 < d {
                pe[p * d + i + 1] = a.cos();
            }
        }
    }
    pe
}

impl InstructionEncoder {
    /// Loads `readout`, `instruction_embedding` and `scene_instruction_encoder.layers.*`
    /// from `s`; the depth is the number of layers present.
    pub fn load(s: &Scope<'_>, heads: usize, dim_head: usize) -> Result<Self> {
        let embed = Linear::load(&s.sub("instruction_embedding"), true)?;
        let dim = embed.out;
        let readout = s.f32("readout", &[1, 1, dim])?;
        let inner = heads * dim_head;
        let layers_scope = s.sub("scene_instruction_encoder").sub("layers");
        let mut layers = Vec::new();
        while layers_scope.contains(&format!("{}.0.norm.weight", layers.len())) {
            let l = layers_scope.sub(&layers.len().to_string());
            let a = l.sub("0");
            let f = l.sub("1").sub("net");
            let ff1 = Linear::load(&f.sub("1"), true)?;
            layers.push(EncoderLayer {
                attn_norm: LayerNorm::load(&a.sub("norm"), dim)?,
                to_qkv: Linear::load_sized(&a.sub("to_qkv"), 3 * inner, dim, false)?,
                to_out: Linear::load_sized(&a.sub("to_out"), dim, inner, false)?,
                ff_norm: LayerNorm::load(&f.sub("0"), dim)?,
                ff2: Linear::load_sized(&f.sub("3"), dim, ff1.out, true)?,
                ff1,
            });
        }
        if layers.is_empty() {
            return Err(PolicyError::MissingTensor {
                name: layers_scope.key("0.0.norm.weight"),
                file: "instruction encoder weights".into(),
            });
        }
        Ok(Self {
            dim,
            heads,
            dim_head,
            readout,
            embed,
            layers,
        })
    }

    /// Width of the input token embeddings.
    pub fn token_dim(&self) -> usize {
        self.embed.inp
    }

    /// The projected tokens with the readout in front, before positions: `[B, T+1, dim]`.
    pub fn tokens_in(&self, instruction: &[f32], batch: usize) -> Result<Vec<f32>> {
        let per = rows_of("instruction", instruction.len(), batch.max(1))?;
        let t = rows_of("instruction tokens", per, self.embed.inp)?;
        let proj = self.embed.forward(instruction)?;
        let mut out = Vec::with_capacity(batch * (t + 1) * self.dim);
        for b in 0..batch {
            out.extend_from_slice(&self.readout);
            out.extend_from_slice(&proj[b * t * self.dim..(b + 1) * t * self.dim]);
        }
        Ok(out)
    }

    /// Encodes `instruction` `[B, T, token_dim]`; returns all output tokens `[B, T+1, dim]`.
    pub fn forward(&self, instruction: &[f32], batch: usize) -> Result<Vec<f32>> {
        let mut x = self.tokens_in(instruction, batch)?;
        let n = rows_of("instruction tokens", x.len(), batch.max(1) * self.dim)?;
        let pe = positional_encoding(n, self.dim);
        for row in x.chunks_exact_mut(n * self.dim) {
            for (a, b) in row.iter_mut().zip(&pe) {
                *a += b;
            }
        }
        for layer in &self.layers {
            for seq in x.chunks_exact_mut(n * self.dim) {
                self.layer_forward(layer, seq, n)?;
            }
        }
        Ok(x)
    }

    /// The FiLM condition (output token 0) for each batch element: `[B, dim]`.
    pub fn condition(&self, instruction: &[f32], batch: usize) -> Result<Vec<f32>> {
        let tokens = self.forward(instruction, batch)?;
        let n = tokens.len() / (batch.max(1) * self.dim);
        Ok(tokens
            .chunks_exact(n * self.dim)
            .flat_map(|s| s[..self.dim].iter().copied())
            .collect())
    }

    fn layer_forward(&self, layer: &EncoderLayer, x: &mut [f32], n: usize) -> Result<()> {
        let d = self.dim;
        let inner = self.heads * self.dim_head;
        let mut h = x.to_vec();
        layer.attn_norm.apply(&mut h);
        let qkv = layer.to_qkv.forward(&h)?;
        let scale = 1.0 / (self.dim_head as f64).sqrt();
        let mut o = vec![0.0f32; n * inner];
        let mut w = vec![0.0f64; n];
        for hd in 0..self.heads {
            let col = hd * self.dim_head;
            for i in 0..n {
                let q = &qkv[i * 3 * inner + col..i * 3 * inner + col + self.dim_head];
                let mut max = f64::NEG_INFINITY;
                for (j, wj) in w.iter_mut().enumerate() {
                    let kj = &qkv
                        [j * 3 * inner + inner + col..j * 3 * inner + inner + col + self.dim_head];
                    let s: f64 = q
                        .iter()
                        .zip(kj)
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
                let oi = &mut o[i * inner + col..i * inner + col + self.dim_head];
                for (j, wj) in w.iter().enumerate() {
                    let vj = &qkv[j * 3 * inner + 2 * inner + col
                        ..j * 3 * inner + 2 * inner + col + self.dim_head];
                    let a = (wj / sum) as f32;
                    for (oc, vc) in oi.iter_mut().zip(vj) {
                        *oc += a * vc;
                    }
                }
            }
        }
        let attn = layer.to_out.forward(&o)?;
        for (a, b) in x.iter_mut().zip(&attn) {
            *a += b;
        }
        let mut h = x.to_vec();
        layer.ff_norm.apply(&mut h);
        let mut f = layer.ff1.forward(&h)?;
        for v in &mut f {
            *v = gelu(*v);
        }
        let f = layer.ff2.forward(&f)?;
        for (a, b) in x.iter_mut().zip(&f) {
            *a += b;
        }
        debug_assert_eq!(x.len(), n * d);
        Ok(())
    }
}
