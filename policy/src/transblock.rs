//! The EquiformerV2 `TransBlock` with the (optionally FiLM-conditioned) feed-forward network.
//!
//! Spec: `equact.md` ("EquiformerV2 block", "iFiLM in the code") and the `transblock`
//! sidecar: h = GA(norm_1_src(x_src), norm_1_dst(x_dst)) + x_dst; y = FFN(norm_2(h)) +
//! shortcut(h), where the shortcut is an `SO3_LinearV2` when the channel count changes.
//! FFN: gating = Linear(l = 0 row); u = (FiLM) SO3 linear; separable S2 activation on the
//! (lmax, lmax) grid; `SO3_LinearV2`. The first linear is plain, the reference's
//! hypernetwork iFiLM, or the paper's per-degree scalar iFiLM ([`FilmKind`]).

use std::sync::Arc;

use crate::attention::{AttentionConfig, EdgeSet, GraphAttention};
use crate::error::{PolicyError, Result};
use crate::grids::S2Grid;
use crate::layers::{
    rows_of, separable_s2_activation, FilmLinear, Linear, PreparedFilm, RmsNormSh,
    ScalarFilmLinear, So3Linear,
};
use crate::so3::num_coefficients;
use crate::weights::Scope;

/// How the feed-forward network's first linear map reads the instruction condition.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub enum FilmKind {
    /// The reference code's `SO3_FiLM_Linear`: a hypernetwork generates every per-degree
    /// weight matrix (`so3_linear_1.cond_encoder.1.*`; most of the model's parameters).
    #[default]
    Hypernetwork,
    /// The paper's form: a plain `SO3_LinearV2` (`so3_linear_1.weight/bias`) scaled per
    /// (degree, channel) and shifted on l = 0 by a small Linear of Mish(condition)
    /// (`so3_linear_1.film.weight/bias`); see [`ScalarFilmLinear`].
    PerDegreeScalar,
}

/// The first linear map of the feed-forward network.
#[derive(Debug, Clone)]
pub enum FirstLinear {
    /// Plain `SO3_LinearV2`.
    Plain(So3Linear),
    /// `SO3_FiLM_Linear` conditioned on the instruction.
    Film(FilmLinear),
    /// The paper's per-degree scalar iFiLM conditioned on the instruction.
    ScalarFilm(ScalarFilmLinear),
}

/// `FeedForwardNetwork` with the separable S2 activation.
#[derive(Debug, Clone)]
pub struct FeedForward {
    /// Maximum degree.
    pub lmax: usize,
    /// Input channels.
    pub cin: usize,
    /// Hidden channels.
    pub hidden: usize,
    /// Output channels.
    pub cout: usize,
    gating: Linear,
    first: FirstLinear,
    grid: S2Grid,
    second: So3Linear,
}

impl FeedForward {
    /// Loads `gating_linear`, `so3_linear_1` (conditioned as `film` says; `None`: plain) and
    /// `so3_linear_2`, with the reference's (lmax, lmax) S2 grid.
    pub fn load(
        s: &Scope<'_>,
        lmax: usize,
        cin: usize,
        hidden: usize,
        cout: usize,
        film: Option<FilmKind>,
    ) -> Result<Self> {
        Self::load_with_grid(
            s,
            lmax,
            cin,
            hidden,
            cout,
            film,
            S2Grid::reference(lmax, lmax)?,
        )
    }

    /// As [`FeedForward::load`] with a given (lmax, lmax) S2 grid.
    pub fn load_with_grid(
        s: &Scope<'_>,
        lmax: usize,
        cin: usize,
        hidden: usize,
        cout: usize,
        film: Option<FilmKind>,
        grid: S2Grid,
    ) -> Result<Self> {
        if grid.lmax != lmax || grid.mmax != lmax {
            return Err(PolicyError::UnsupportedDegree {
                lmax: grid.lmax,
                mmax: grid.mmax,
                max_supported: lmax,
            });
        }
        let gating = Linear::load_sized(&s.sub("gating_linear"), hidden, cin, true)?;
        let first = match film {
            Some(FilmKind::Hypernetwork) => {
                FirstLinear::Film(FilmLinear::load(&s.sub("so3_linear_1"), lmax, cin, hidden)?)
            }
            Some(FilmKind::PerDegreeScalar) => {
                let f = ScalarFilmLinear::load(&s.sub("so3_linear_1"))?;
                check_so3(s, "so3_linear_1", f.linear(), lmax, cin, hidden)?;
                FirstLinear::ScalarFilm(f)
            }
            None => {
                let l = So3Linear::load(&s.sub("so3_linear_1"))?;
                check_so3(s, "so3_linear_1", &l, lmax, cin, hidden)?;
                FirstLinear::Plain(l)
            }
        };
        let second = So3Linear::load(&s.sub("so3_linear_2"))?;
        check_so3(s, "so3_linear_2", &second, lmax, hidden, cout)?;
        Ok(Self {
            lmax,
            cin,
            hidden,
            cout,
            gating,
            first,
            grid,
            second,
        })
    }

    /// Applies the network to `x` `[n, (lmax+1)², cin]`; `condition` `[B, dim]` is required
    /// with FiLM (nodes grouped by batch, equal counts).
    pub fn forward(&self, x: &[f32], condition: Option<&[f32]>) -> Result<Vec<f32>> {
        self.forward_prepared(x, condition, None)
    }

    /// The hypernetwork FiLM's map for a single condition row (`None` for the other first
    /// linears, or several rows), on `threads` threads: computed once per forward pass.
    pub fn prepare(
        &self,
        condition: Option<&[f32]>,
        threads: usize,
    ) -> Result<Option<Arc<PreparedFilm>>> {
        match (&self.first, condition) {
            (FirstLinear::Film(f), Some(c)) if c.len() == f.condition_dim() => {
                Ok(Some(f.prepare(c, threads)?))
            }
            _ => Ok(None),
        }
    }

    /// [`FeedForward::forward`] with the FiLM map of [`FeedForward::prepare`] when given.
    pub fn forward_prepared(
        &self,
        x: &[f32],
        condition: Option<&[f32]>,
        prepared: Option<&PreparedFilm>,
    ) -> Result<Vec<f32>> {
        let k = num_coefficients(self.lmax);
        let n = rows_of("feed-forward input", x.len(), k * self.cin)?;
        let mut l0 = Vec::with_capacity(n * self.cin);
        for node in 0..n {
            l0.extend_from_slice(&x[node * k * self.cin..node * k * self.cin + self.cin]);
        }
        let gating = self.gating.forward(&l0)?;
        let u = match (&self.first, condition, prepared) {
            (FirstLinear::Film(f), _, Some(p)) => f.apply(x, p)?,
            (FirstLinear::Plain(l), _, _) => l.forward(x)?,
            (FirstLinear::Film(f), Some(c), None) => f.forward(x, c)?,
            (FirstLinear::ScalarFilm(f), Some(c), _) => f.forward(x, c)?,
            (FirstLinear::Film(_) | FirstLinear::ScalarFilm(_), None, _) => {
                return Err(PolicyError::ShapeMismatch {
                    name: "FiLM condition (required by this feed-forward network)".into(),
                    expected: vec![1, self.condition_dim().unwrap_or(0)],
                    got: vec![0],
                })
            }
        };
        let u = separable_s2_activation(&self.grid, &gating, &u, self.hidden)?;
        self.second.forward(&u)
    }

    /// Width of the condition the first linear reads (`None` when it is not conditioned).
    pub fn condition_dim(&self) -> Option<usize> {
        match &self.first {
            FirstLinear::Plain(_) => None,
            FirstLinear::Film(f) => Some(f.condition_dim()),
            FirstLinear::ScalarFilm(f) => Some(f.condition_dim()),
        }
    }
}

fn check_so3(
    s: &Scope<'_>,
    name: &str,
    l: &So3Linear,
    lmax: usize,
    cin: usize,
    cout: usize,
) -> Result<()> {
    if l.lmax != lmax || l.cin != cin || l.cout != cout {
        return Err(PolicyError::ShapeMismatch {
            name: s.key(&format!("{name}.weight")),
            expected: vec![lmax + 1, cout, cin],
            got: vec![l.lmax + 1, l.cout, l.cin],
        });
    }
    Ok(())
}

/// Sizes of a [`TransBlock`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TransBlockConfig {
    /// The attention's sizes (its output width must equal its input width).
    pub attn: AttentionConfig,
    /// Hidden channels of the feed-forward network.
    pub ffn_hidden_channels: usize,
    /// Output channels of the block.
    pub output_channels: usize,
    /// How the feed-forward network's first linear is FiLM-conditioned (`None`: plain).
    pub film: Option<FilmKind>,
}

/// `TransBlock`: normed graph attention with a residual, then a normed feed-forward network
/// with a (possibly linear) residual.
#[derive(Debug, Clone)]
pub struct TransBlock {
    /// Sizes.
    pub cfg: TransBlockConfig,
    norm_1_src: RmsNormSh,
    norm_1_dst: RmsNormSh,
    ga: GraphAttention,
    norm_2: RmsNormSh,
    ffn: FeedForward,
    shortcut: Option<So3Linear>,
    /// Threads of a forward pass ([`TransBlock::set_threads`]).
    threads: usize,
}

/// Fewest nodes a thread takes after the attention (fewer cost more to hand over than to
/// compute).
const MIN_NODES_PER_THREAD: usize = 64;

impl TransBlock {
    /// Threads of the block: its attention, and runs of nodes after it (see
    /// [`crate::parallel`]).
    pub fn set_threads(&mut self, threads: usize) {
        self.threads = threads.max(1);
        self.ga.set_threads(threads);
    }

    /// Loads the block's modules (`norm_1_src`, `norm_1_dst`, `ga`, `norm_2`, `ffn`,
    /// `ffn_shortcut`) from `s`, with the reference's S2 grids.
    pub fn load(s: &Scope<'_>, cfg: TransBlockConfig) -> Result<Self> {
        let a = cfg.attn;
        Self::load_with_grids(
            s,
            cfg,
            S2Grid::reference(a.lmax, a.mmax)?,
            S2Grid::reference(a.lmax, a.lmax)?,
        )
    }

    /// As [`TransBlock::load`] with given S2 grids for the attention (lmax, mmax) and the
    /// feed-forward network (lmax, lmax).
    pub fn load_with_grids(
        s: &Scope<'_>,
        cfg: TransBlockConfig,
        attn_grid: S2Grid,
        ffn_grid: S2Grid,
    ) -> Result<Self> {
        let a = cfg.attn;
        if a.output_channels != a.sphere_channels {
            return Err(PolicyError::ShapeMismatch {
                name: s.key("ga.proj.weight (a TransBlock's attention keeps its width)"),
                expected: vec![a.sphere_channels],
                got: vec![a.output_channels],
            });
        }
        let (lmax, c) = (a.lmax, a.sphere_channels);
        let shortcut = if cfg.output_channels != c {
            let l = So3Linear::load(&s.sub("ffn_shortcut"))?;
            check_so3(s, "ffn_shortcut", &l, lmax, c, cfg.output_channels)?;
            Some(l)
        } else {
            None
        };
        Ok(Self {
            cfg,
            norm_1_src: RmsNormSh::load(&s.sub("norm_1_src"), lmax, c)?,
            norm_1_dst: RmsNormSh::load(&s.sub("norm_1_dst"), lmax, c)?,
            ga: GraphAttention::load_with_grid(&s.sub("ga"), a, attn_grid)?,
            norm_2: RmsNormSh::load(&s.sub("norm_2"), lmax, c)?,
            ffn: FeedForward::load_with_grid(
                &s.sub("ffn"),
                lmax,
                c,
                cfg.ffn_hidden_channels,
                cfg.output_channels,
                cfg.film,
                ffn_grid,
            )?,
            shortcut,
            threads: 1,
        })
    }

    /// Applies the block: messages from `x_src` to `x_dst` over `edges`; returns
    /// `[Nd, (lmax+1)², output_channels]`.
    pub fn forward(
        &self,
        x_src: &[f32],
        x_dst: &[f32],
        edges: &EdgeSet,
        condition: Option<&[f32]>,
    ) -> Result<Vec<f32>> {
        // The norms, and everything after the attention, are per node: with threads, runs of
        // whole nodes go to each (one condition row serves every node; several rows group
        // the nodes by batch, so those stay on one thread). Products over fewer rows sum each
        // output in the same order, so the values do not change.
        let k = num_coefficients(self.cfg.attn.lmax);
        let row = k * self.cfg.attn.sphere_channels;
        let par = (self.threads, MIN_NODES_PER_THREAD);
        let xs = crate::parallel::map_rows(x_src, row, par, |x| self.norm_1_src.forward(x))?;
        let xd = crate::parallel::map_rows(x_dst, row, par, |x| self.norm_1_dst.forward(x))?;
        let mut h = self.ga.forward(&xs, &xd, edges)?;
        for (a, b) in h.iter_mut().zip(x_dst) {
            *a += b;
        }
        let one_condition = condition.is_none_or(|c| Some(c.len()) == self.ffn.condition_dim());
        let par = if one_condition { par } else { (1, 1) };
        // The hypernetwork's map is the same for every node: made once, on all the threads.
        let film = self.ffn.prepare(condition, self.threads)?;
        crate::parallel::map_rows(&h, row, par, |h| {
            let n = self.norm_2.forward(h)?;
            let mut y = self.ffn.forward_prepared(&n, condition, film.as_deref())?;
            let shortcut;
            let res = match &self.shortcut {
                Some(l) => {
                    shortcut = l.forward(h)?;
                    &shortcut
                }
                None => h,
            };
            for (a, b) in y.iter_mut().zip(res) {
                *a += b;
            }
            Ok(y)
        })
    }
}
