//! Seeded random parameters for a whole `EquFieldUnet`, so the policy runs (and is
//! benchmarked) without a checkpoint.
//!
//! The key names and shapes are the reference's `state_dict()` layout for the given sizes (the
//! same layout [`crate::model::EquFieldUnet::load`] reads). Values follow the fixtures' scheme
//! (fixtures README, "Parameters"), which keeps every intermediate O(1): matrices N(0,1)/√fan_in,
//! biases 0.2·N(0,1), norm weights 1 + 0.1·N(0,1), norm biases 0.1·N(0,1), `alpha_dot`
//! N(0,1)/√alpha, `S2Conv.w` 0.1·N(0,1), readout N(0,1); radial-basis means at
//! (k+1)/(K+1), widths softplus⁻¹(2/(K+1)), amplitudes 4σ(logit 0.25) = 1, each with a little
//! noise.

use std::collections::HashMap;

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::fixtures::{StoredTensor, TensorData};
use crate::heads::{ROT_LMAX, ROT_MMAX, TRANS_LMAX};
use crate::model::{HeadKind, ModelConfig};
use crate::plain_heads::{PlainHeadsConfig, PLAIN_ROT_OUTPUTS, PLAIN_ROT_SCOPE, PLAIN_TRANS_SCOPE};
use crate::transblock::FilmKind;
use crate::weights::Weights;

/// Sizes the loader infers from the tensors but a generator must be told.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ExtraSizes {
    /// Hidden width of each scale's radial MLP (`edge_channels`).
    pub edge_channels: Vec<usize>,
    /// Radial basis functions of the U-net blocks (`num_distance_basis`).
    pub num_distance_basis: usize,
    /// Radial basis functions of the field heads (1024 in the reference).
    pub field_num_basis: usize,
    /// Width of the FiLM condition and the instruction Transformer (`film_dim`).
    pub film_dim: usize,
    /// Width of the instruction token embeddings (512 for CLIP).
    pub token_dim: usize,
    /// Depth of the instruction Transformer.
    pub lang_depth: usize,
    /// Hidden width of the instruction Transformer's MLP.
    pub lang_mlp: usize,
}

impl ExtraSizes {
    /// The reference's defaults (physical-robot configuration).
    pub fn reference() -> Self {
        Self {
            edge_channels: vec![16, 16, 32, 64],
            num_distance_basis: 128,
            field_num_basis: 1024,
            film_dim: 128,
            token_dim: 512,
            lang_depth: 4,
            lang_mlp: 256,
        }
    }
}

#[derive(Clone, Copy)]
enum Init {
    /// N(0,1)/√fan_in, fan_in = last axis.
    Matrix,
    /// 0.2·N(0,1).
    Bias,
    /// 1 + 0.1·N(0,1).
    NormWeight,
    /// 0.1·N(0,1).
    NormBias,
    /// scale·N(0,1).
    Scaled(f32),
    /// RBF means (k+1)/(K+1) + 0.1/K·N(0,1).
    RbfMean,
    /// softplus⁻¹(2/(K+1)) + 0.2·N(0,1).
    RbfStd,
    /// logit(0.25) + 0.2·N(0,1).
    RbfWeight,
}

struct Gen {
    rng: ChaCha8Rng,
    spare: Option<f64>,
    out: HashMap<String, StoredTensor>,
}

impl Gen {
    /// A standard normal sample (Box–Muller, both values used).
    fn normal(&mut self) -> f32 {
        if let Some(v) = self.spare.take() {
            return v as f32;
        }
        let u1: f64 = 1.0 - self.rng.random::<f64>();
        let u2: f64 = self.rng.random::<f64>();
        let r = (-2.0 * u1.ln()).sqrt();
        let t = std::f64::consts::TAU * u2;
        self.spare = Some(r * t.sin());
        (r * t.cos()) as f32
    }

    fn add(&mut self, key: String, shape: &[usize], init: Init) {
        let n: usize = shape.iter().product();
        let last = shape.last().copied().unwrap_or(1).max(1);
        let mut v = Vec::with_capacity(n);
        for i in 0..n {
            let z = self.normal();
            v.push(match init {
                Init::Matrix => z / (last as f32).sqrt(),
                Init::Bias => 0.2 * z,
                Init::NormWeight => 1.0 + 0.1 * z,
                Init::NormBias => 0.1 * z,
                Init::Scaled(s) => s * z,
                Init::RbfMean => (i + 1) as f32 / (last + 1) as f32 + 0.1 / last as f32 * z,
                Init::RbfStd => {
                    let s = 2.0 / (last + 1) as f64;
                    (s.exp_m1().ln() as f32) + 0.2 * z
                }
                Init::RbfWeight => (1.0f32 / 3.0).ln() + 0.2 * z,
            });
        }
        self.out.insert(
            key,
            StoredTensor {
                shape: shape.to_vec(),
                data: TensorData::F32(v),
            },
        );
    }

    fn linear(&mut self, p: &str, out: usize, inp: usize, bias: bool) {
        self.add(format!("{p}weight"), &[out, inp], Init::Matrix);
        if bias {
            self.add(format!("{p}bias"), &[out], Init::Bias);
        }
    }

    fn layer_norm(&mut self, p: &str, dim: usize) {
        self.add(format!("{p}weight"), &[dim], Init::NormWeight);
        self.add(format!("{p}bias"), &[dim], Init::NormBias);
    }

    fn rms_norm(&mut self, p: &str, lmax: usize, c: usize) {
        self.add(
            format!("{p}affine_weight"),
            &[lmax + 1, c],
            Init::NormWeight,
        );
        self.add(format!("{p}affine_bias"), &[c], Init::NormBias);
    }

    fn so3_linear(&mut self, p: &str, lmax: usize, cout: usize, cin: usize) {
        self.add(format!("{p}weight"), &[lmax + 1, cout, cin], Init::Matrix);
        self.add(format!("{p}bias"), &[cout], Init::Bias);
    }

    fn rbf(&mut self, p: &str, k: usize) {
        self.add(format!("{p}mean"), &[1, k], Init::RbfMean);
        self.add(format!("{p}std_logit"), &[1, k], Init::RbfStd);
        self.add(format!("{p}weight_logit"), &[1, k], Init::RbfWeight);
    }

    /// `SO2_Convolution` with `extra` m = 0 outputs and, when `rad` is given as
    /// (basis, hidden), its radial MLP.
    #[allow(clippy::too_many_arguments)]
    fn so2_conv(
        &mut self,
        p: &str,
        lmax: usize,
        mmax: usize,
        cin: usize,
        cout: usize,
        extra: usize,
        rad: Option<(usize, usize)>,
    ) {
        let l1 = lmax + 1;
        self.linear(&format!("{p}fc_m0."), extra + l1 * cout, l1 * cin, true);
        let mut width = l1 * cin;
        for m in 1..=mmax {
            let nl = l1 - m;
            self.linear(
                &format!("{p}so2_m_conv.{}.fc.", m - 1),
                2 * nl * cout,
                nl * cin,
                false,
            );
            width += nl * cin;
        }
        if let Some((basis, hidden)) = rad {
            self.linear(&format!("{p}rad_func.net.0."), hidden, basis, true);
            self.layer_norm(&format!("{p}rad_func.net.1."), hidden);
            self.linear(&format!("{p}rad_func.net.3."), hidden, hidden, true);
            self.layer_norm(&format!("{p}rad_func.net.4."), hidden);
            self.linear(&format!("{p}rad_func.net.6."), width, hidden, true);
        }
    }

    /// A plain transformer head layer ([`crate::plain_heads`]) with `n_out` readout
    /// outputs; `readout` initialises the readout matrix.
    fn plain_layer(&mut self, p: &str, sz: PlainHeadsConfig, n_out: usize, readout: Init) {
        let (c, inner, f) = (sz.channels, sz.inner(), sz.ffn_hidden);
        self.add(format!("{p}query"), &[c], Init::Scaled(1.0));
        self.linear(&format!("{p}query_pos."), c, 3, false);
        self.layer_norm(&format!("{p}norm_q."), c);
        self.layer_norm(&format!("{p}norm_kv."), c + 3);
        self.linear(&format!("{p}to_q."), inner, c, false);
        self.linear(&format!("{p}to_k."), inner, c + 3, false);
        self.linear(&format!("{p}to_v."), inner, c + 3, false);
        self.linear(&format!("{p}to_out."), c, inner, true);
        self.layer_norm(&format!("{p}norm_ff."), c);
        self.linear(&format!("{p}ff1."), f, c, true);
        self.linear(&format!("{p}ff2."), c, f, true);
        self.layer_norm(&format!("{p}norm_out."), c);
        self.add(format!("{p}readout.weight"), &[n_out, c], readout);
        self.add(format!("{p}readout.bias"), &[n_out], Init::Bias);
    }

    /// `SO2EquivariantGraphAttention` (output width = input width).
    #[allow(clippy::too_many_arguments)]
    fn attention(
        &mut self,
        p: &str,
        lmax: usize,
        mmax: usize,
        c: usize,
        hidden: usize,
        heads: usize,
        alpha: usize,
        value: usize,
        rad: (usize, usize),
    ) {
        self.add(
            format!("{p}alpha_dot"),
            &[heads, alpha],
            Init::Scaled(1.0 / (alpha as f32).sqrt()),
        );
        self.so2_conv(
            &format!("{p}so2_conv_1."),
            lmax,
            mmax,
            2 * c,
            hidden,
            heads * alpha + hidden,
            Some(rad),
        );
        self.layer_norm(&format!("{p}alpha_norm."), alpha);
        self.so2_conv(
            &format!("{p}so2_conv_2."),
            lmax,
            mmax,
            hidden,
            heads * value,
            0,
            None,
        );
        self.so3_linear(&format!("{p}proj."), lmax, c, heads * value);
    }
}

/// Seeded random parameters for `cfg` (and the sizes in `extra`), keys without prefix; the
/// U-net feed-forward networks' first linear follows `cfg.film_kind` (the per-degree scalar
/// iFiLM's modulation weights are 0.1·N(0,1)/√film_dim, its biases 0.1·N(0,1)).
pub fn random_weights(cfg: &ModelConfig, extra: &ExtraSizes, seed: u64) -> Weights {
    let mut g = Gen {
        rng: ChaCha8Rng::seed_from_u64(seed),
        spare: None,
        out: HashMap::new(),
    };
    let n = cfg.n_scales();
    let (lmax, mmax) = (cfg.lmax, cfg.mmax);
    let film = extra.film_dim;
    // Instruction encoder.
    g.linear("instruction_embedding.", film, extra.token_dim, true);
    g.add("readout".into(), &[1, 1, film], Init::Scaled(1.0));
    let inner = cfg.lang_heads * cfg.lang_dim_head;
    for i in 0..extra.lang_depth {
        let p = format!("scene_instruction_encoder.layers.{i}.");
        g.layer_norm(&format!("{p}0.norm."), film);
        g.linear(&format!("{p}0.to_qkv."), 3 * inner, film, false);
        g.linear(&format!("{p}0.to_out."), film, inner, false);
        g.layer_norm(&format!("{p}1.net.0."), film);
        g.linear(&format!("{p}1.net.1."), extra.lang_mlp, film, true);
        g.linear(&format!("{p}1.net.3."), film, extra.lang_mlp, true);
    }
    let sc = &cfg.sphere_channels;
    g.linear("type0_linear.", sc[0], 3, true);
    let ec = |i: usize| extra.edge_channels.get(i).copied().unwrap_or(16);
    let block = |g: &mut Gen, p: String, i: usize, cin: usize, cout: usize| {
        g.rbf(&format!("{p}distance_expansion."), extra.num_distance_basis);
        let t = format!("{p}transblock.");
        g.rms_norm(&format!("{t}norm_1_src."), lmax, cin);
        g.rms_norm(&format!("{t}norm_1_dst."), lmax, cin);
        g.attention(
            &format!("{t}ga."),
            lmax,
            mmax,
            cin,
            cfg.attn_hidden_channels[i],
            cfg.num_heads,
            cfg.attn_alpha_channels[i],
            cfg.attn_value_channels[i],
            (extra.num_distance_basis, ec(i)),
        );
        g.rms_norm(&format!("{t}norm_2."), lmax, cin);
        let hidden = cfg.ffn_hidden_channels[i];
        match cfg.film_kind {
            FilmKind::Hypernetwork => g.linear(
                &format!("{t}ffn.so3_linear_1.cond_encoder.1."),
                (lmax + 1) * hidden * cin + hidden,
                film,
                true,
            ),
            FilmKind::PerDegreeScalar => {
                g.so3_linear(&format!("{t}ffn.so3_linear_1."), lmax, hidden, cin);
                // Small modulation weights: the layer starts near its plain linear map.
                let p = format!("{t}ffn.so3_linear_1.film.");
                let out = (lmax + 2) * hidden;
                let scale = 0.1 / (film.max(1) as f32).sqrt();
                g.add(format!("{p}weight"), &[out, film], Init::Scaled(scale));
                g.add(format!("{p}bias"), &[out], Init::NormBias);
            }
        }
        g.linear(&format!("{t}ffn.gating_linear."), hidden, cin, true);
        g.so3_linear(&format!("{t}ffn.so3_linear_2."), lmax, cout, hidden);
        if cout != cin {
            g.so3_linear(&format!("{t}ffn_shortcut."), lmax, cout, cin);
        }
    };
    for i in 0..n {
        block(
            &mut g,
            format!("down_blocks.{i}.block."),
            i,
            sc[i],
            sc[i + 1],
        );
    }
    block(&mut g, "middle_block.block.".into(), n - 1, sc[n], sc[n]);
    for (j, i) in (0..n).rev().enumerate() {
        let cout = if i == 0 { cfg.field_nn_c } else { sc[i] };
        block(&mut g, format!("up_blocks.{j}.block."), i, sc[i + 1], cout);
    }
    let c = cfg.field_nn_c;
    g.rms_norm("norm_1.", lmax, c);
    match cfg.heads {
        HeadKind::Equivariant => equivariant_heads(&mut g, cfg, extra),
        HeadKind::Plain => {
            // Widths as `PlainHeadsConfig::of` takes them (a short list falls back to 1 and
            // fails at load with a typed error).
            let at1 = |v: &[usize]| v.get(1).copied().unwrap_or(1);
            let sizes = PlainHeadsConfig {
                channels: c,
                num_heads: cfg.num_heads,
                head_dim: at1(&cfg.attn_alpha_channels),
                ffn_hidden: at1(&cfg.ffn_hidden_channels),
                node_lmax: lmax,
            };
            g.plain_layer(&format!("{PLAIN_TRANS_SCOPE}."), sizes, 1, Init::Matrix);
            // A small SO(3) signal at the start, like `s2_conv.w`'s 0.1 scale.
            let small = Init::Scaled(0.1 / (c.max(1) as f32).sqrt());
            g.plain_layer(
                &format!("{PLAIN_ROT_SCOPE}."),
                sizes,
                PLAIN_ROT_OUTPUTS,
                small,
            );
        }
    }
    Weights::from_tensors(&format!("random weights (seed {seed})"), g.out)
}

/// The equivariant field heads' parameters (`field_distance_expansion`,
/// `trans_field_layer.0`, `rot_field_layer.0`, `s2_conv.w`).
fn equivariant_heads(g: &mut Gen, cfg: &ModelConfig, extra: &ExtraSizes) {
    let c = cfg.field_nn_c;
    let ec = |i: usize| extra.edge_channels.get(i).copied().unwrap_or(16);
    g.rbf("field_distance_expansion.", extra.field_num_basis);
    let rad = (extra.field_num_basis, ec(1));
    g.attention(
        "trans_field_layer.0.",
        TRANS_LMAX,
        TRANS_LMAX,
        c,
        cfg.attn_hidden_channels[1],
        cfg.num_heads,
        cfg.attn_alpha_channels[1],
        cfg.attn_value_channels[1],
        rad,
    );
    let t = "rot_field_layer.0.";
    g.rms_norm(&format!("{t}norm_1_src."), ROT_LMAX, c);
    g.rms_norm(&format!("{t}norm_1_dst."), ROT_LMAX, c);
    g.attention(
        &format!("{t}ga."),
        ROT_LMAX,
        ROT_MMAX,
        c,
        cfg.attn_hidden_channels[1],
        cfg.num_heads,
        cfg.attn_alpha_channels[1],
        cfg.attn_value_channels[1],
        rad,
    );
    g.rms_norm(&format!("{t}norm_2."), ROT_LMAX, c);
    let hidden = cfg.ffn_hidden_channels[1];
    g.so3_linear(&format!("{t}ffn.so3_linear_1."), ROT_LMAX, hidden, c);
    g.linear(&format!("{t}ffn.gating_linear."), hidden, c, true);
    g.so3_linear(&format!("{t}ffn.so3_linear_2."), ROT_LMAX, c, hidden);
    g.add(
        "s2_conv.w".into(),
        &[c.saturating_sub(1), 1, 48],
        Init::Scaled(0.1),
    );
}
