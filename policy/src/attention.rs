//! Equivariant graph attention (`SO2EquivariantGraphAttention`) and the edge sets it runs on.
//!
//! Spec: fixtures README ("Edges", "Attention") and the `graph_attention` sidecar. Messages
//! `concat(x_src[src], x_dst[dst])` are rotated into each edge's frame, go through an SO(2)
//! convolution (radial weights, extra m = 0 outputs: attention logits then gating scalars),
//! the separable S2 activation and a second SO(2) convolution; each head's values are
//! weighted by a softmax over the edges sharing a destination, rotated back, summed at the
//! destination and projected by an `SO3_LinearV2`.

use std::sync::Arc;

use crate::error::{PolicyError, Result};
use crate::grids::S2Grid;
use crate::layers::{
    check_len, rows_of, separable_s2_activation, smooth_leaky_relu_of, EdgeFeatures,
    EdgeFeaturesRef, GaussianRbf, LayerNorm, So3Linear,
};
use crate::so2_conv::{CoefficientMapping, EdgeWigners, M0Block, MProducts, So2Conv};
use crate::so3::{num_coefficients, WignerCalculator};
use crate::weights::Scope;

/// A set of directed edges with their frames and invariant features.
#[derive(Debug, Clone)]
pub struct EdgeSet {
    /// Source node of each edge (index into the source features).
    pub src: Vec<usize>,
    /// Destination node of each edge (index into the destination features).
    pub dst: Vec<usize>,
    /// Edge vectors `pos_src[src] − pos_dst[dst]`.
    pub vec: Vec<[f32; 3]>,
    /// Edge lengths.
    pub dist: Vec<f32>,
    /// Wigner matrices of the edge frames (shared by edge sets of the same edges, see
    /// [`EdgeSet::with_rbf`]).
    pub wigners: Arc<EdgeWigners>,
    /// Invariant edge features (radial basis of the length), `[E, num_basis]`.
    pub attr: EdgeFeatures,
}

/// The edge vectors `pos_src[src[e]] − pos_dst[dst[e]]`.
pub fn edge_vectors(
    pos_src: &[[f32; 3]],
    pos_dst: &[[f32; 3]],
    src: &[usize],
    dst: &[usize],
) -> Result<Vec<[f32; 3]>> {
    let mut vec = Vec::with_capacity(src.len());
    for (&s, &d) in src.iter().zip(dst) {
        let (Some(ps), Some(pd)) = (pos_src.get(s), pos_dst.get(d)) else {
            return Err(PolicyError::IndexOutOfRange {
                name: "edge_src/edge_dst".into(),
                value: s.max(d) as i64,
                len: pos_src.len().min(pos_dst.len()),
            });
        };
        vec.push([ps[0] - pd[0], ps[1] - pd[1], ps[2] - pd[2]]);
    }
    Ok(vec)
}

/// The radial basis of every length, split over `threads` threads (the same rows).
fn rbf_features_threads(rbf: &GaussianRbf, dist: &[f32], threads: usize) -> Result<EdgeFeatures> {
    let parts = crate::parallel::split_even(dist.len(), threads.min(dist.len() / 256));
    if parts.len() > 1 {
        EdgeFeatures::concat(crate::parallel::run_parts(parts, |r| {
            rbf.features(&dist[r])
        }))
    } else {
        Ok(rbf.features(dist))
    }
}

/// Euclidean length of each edge vector.
fn edge_lengths(vec: &[[f32; 3]]) -> Vec<f32> {
    vec.iter()
        .map(|v| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt())
        .collect()
}

impl EdgeSet {
    /// Builds the edges `src[e] → dst[e]` between two point sets, with the radial basis
    /// `rbf` of their lengths and frames up to degree `lmax`.
    pub fn new(
        calc: &WignerCalculator,
        lmax: usize,
        pos_src: &[[f32; 3]],
        pos_dst: &[[f32; 3]],
        src: Vec<usize>,
        dst: Vec<usize>,
        rbf: &GaussianRbf,
    ) -> Result<Self> {
        Self::new_threads(calc, lmax, (pos_src, pos_dst), src, dst, rbf, 1)
    }

    /// [`EdgeSet::new`] with the frames and radial bases computed on `threads` threads (the
    /// same edge set).
    pub fn new_threads(
        calc: &WignerCalculator,
        lmax: usize,
        (pos_src, pos_dst): (&[[f32; 3]], &[[f32; 3]]),
        src: Vec<usize>,
        dst: Vec<usize>,
        rbf: &GaussianRbf,
        threads: usize,
    ) -> Result<Self> {
        if src.len() != dst.len() {
            return Err(PolicyError::ShapeMismatch {
                name: "edge_dst".into(),
                expected: vec![src.len()],
                got: vec![dst.len()],
            });
        }
        let vec = edge_vectors(pos_src, pos_dst, &src, &dst)?;
        let dist = edge_lengths(&vec);
        let attr = rbf_features_threads(rbf, &dist, threads)?;
        Self::assemble(calc, lmax, (src, dst), (vec, dist), attr, threads)
    }

    /// The same edges (and the same frames, shared, not copied) with the radial basis `rbf`
    /// of their lengths on `threads` threads: a U-net up block runs on its down block's
    /// nodes and graph, only its radial basis differs.
    pub fn with_rbf(&self, rbf: &GaussianRbf, threads: usize) -> Result<Self> {
        Ok(Self {
            src: self.src.clone(),
            dst: self.dst.clone(),
            vec: self.vec.clone(),
            dist: self.dist.clone(),
            wigners: Arc::clone(&self.wigners),
            attr: rbf_features_threads(rbf, &self.dist, threads)?,
        })
    }

    /// Builds an edge set from given edge vectors and features (e.g. a fixture's).
    pub fn from_parts(
        calc: &WignerCalculator,
        lmax: usize,
        src: Vec<usize>,
        dst: Vec<usize>,
        vec: Vec<[f32; 3]>,
        attr: Vec<f32>,
    ) -> Result<Self> {
        let e = src.len();
        check_len("edge_dst", dst.len(), &[e])?;
        check_len("edge_vec", vec.len(), &[e])?;
        let dist = edge_lengths(&vec);
        let attr = EdgeFeatures::dense(attr, e)?;
        Self::assemble(calc, lmax, (src, dst), (vec, dist), attr, 1)
    }

    /// The edge set with its Wigner matrices computed from the edge vectors (on `threads`
    /// threads).
    fn assemble(
        calc: &WignerCalculator,
        lmax: usize,
        (src, dst): (Vec<usize>, Vec<usize>),
        (vec, dist): (Vec<[f32; 3]>, Vec<f32>),
        attr: EdgeFeatures,
        threads: usize,
    ) -> Result<Self> {
        Self::check_attr(&attr, src.len())?;
        let wigners = Arc::new(EdgeWigners::new_threads(calc, lmax, &vec, threads)?);
        Ok(Self {
            src,
            dst,
            vec,
            dist,
            wigners,
            attr,
        })
    }

    /// An error unless `attr` has one row per edge.
    fn check_attr(attr: &EdgeFeatures, edges: usize) -> Result<()> {
        if attr.rows() != edges {
            return Err(PolicyError::ShapeMismatch {
                name: "edge_attr".into(),
                expected: vec![edges, attr.cols()],
                got: vec![attr.rows(), attr.cols()],
            });
        }
        Ok(())
    }

    /// Number of edges.
    pub fn len(&self) -> usize {
        self.src.len()
    }

    /// Whether there are no edges.
    pub fn is_empty(&self) -> bool {
        self.src.is_empty()
    }
}

/// Sizes of a graph attention layer (the reference's constructor arguments).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct AttentionConfig {
    /// Maximum degree.
    pub lmax: usize,
    /// Maximum order kept in the edge frame.
    pub mmax: usize,
    /// Channels of the source and destination features.
    pub sphere_channels: usize,
    /// Channels between the two SO(2) convolutions.
    pub hidden_channels: usize,
    /// Attention heads.
    pub num_heads: usize,
    /// Logit channels per head.
    pub alpha_channels: usize,
    /// Value channels per head.
    pub value_channels: usize,
    /// Output channels.
    pub output_channels: usize,
}

/// `SO2EquivariantGraphAttention` (separable S2 activation, attention re-normalisation, no
/// shared radial weights, eval mode).
#[derive(Debug, Clone)]
pub struct GraphAttention {
    /// Sizes.
    pub cfg: AttentionConfig,
    map: CoefficientMapping,
    conv1: So2Conv,
    conv2: So2Conv,
    alpha_norm: LayerNorm,
    alpha_dot: Vec<f32>,
    grid: S2Grid,
    proj: So3Linear,
    /// `so2_conv_1` on the source half of the messages only, for all-zero destinations
    /// (built by [`GraphAttention::prepare_zero_destinations`]).
    conv1_sources: Option<So2Conv>,
    /// The parts of the invariant readout onto all-zero destinations (built by
    /// [`GraphAttention::prepare_zero_destinations`]).
    readout: Option<InvariantReadout>,
    /// Threads of a forward pass ([`GraphAttention::set_threads`]).
    threads: usize,
    /// How the SO(2) convolutions compute their m > 0 blocks.
    products: MProducts,
}

impl GraphAttention {
    /// Loads `so2_conv_1`, `so2_conv_2`, `alpha_norm`, `alpha_dot` and `proj` from `s`, with
    /// the reference's S2 grid for (lmax, mmax).
    pub fn load(s: &Scope<'_>, cfg: AttentionConfig) -> Result<Self> {
        let grid = S2Grid::reference(cfg.lmax, cfg.mmax)?;
        Self::load_with_grid(s, cfg, grid)
    }

    /// As [`GraphAttention::load`] with a given S2 grid (finer grids: closer to equivariant).
    pub fn load_with_grid(s: &Scope<'_>, cfg: AttentionConfig, grid: S2Grid) -> Result<Self> {
        let map = CoefficientMapping::new(cfg.lmax, cfg.mmax)?;
        let n_alpha = cfg.num_heads * cfg.alpha_channels;
        let conv1 = So2Conv::load(
            &s.sub("so2_conv_1"),
            &map,
            2 * cfg.sphere_channels,
            cfg.hidden_channels,
            n_alpha + cfg.hidden_channels,
            true,
        )?;
        // The gated activation replaces the hidden l = 0 row by SiLU(gating): that row of
        // the first convolution is never read.
        let conv1 = if grid.gated {
            conv1.without_l0_outputs()?
        } else {
            conv1
        };
        let conv2 = So2Conv::load(
            &s.sub("so2_conv_2"),
            &map,
            cfg.hidden_channels,
            cfg.num_heads * cfg.value_channels,
            0,
            false,
        )?;
        let alpha_norm = LayerNorm::load(&s.sub("alpha_norm"), cfg.alpha_channels)?;
        let alpha_dot = s.f32("alpha_dot", &[cfg.num_heads, cfg.alpha_channels])?;
        let proj = So3Linear::load(&s.sub("proj"))?;
        if proj.lmax != cfg.lmax
            || proj.cin != cfg.num_heads * cfg.value_channels
            || proj.cout != cfg.output_channels
        {
            return Err(PolicyError::ShapeMismatch {
                name: s.key("proj.weight"),
                expected: vec![
                    cfg.lmax + 1,
                    cfg.output_channels,
                    cfg.num_heads * cfg.value_channels,
                ],
                got: vec![proj.lmax + 1, proj.cout, proj.cin],
            });
        }
        if grid.lmax != cfg.lmax || grid.reduced != map.reduced {
            return Err(PolicyError::UnsupportedDegree {
                lmax: grid.lmax,
                mmax: grid.mmax,
                max_supported: cfg.lmax,
            });
        }
        Ok(Self {
            cfg,
            map,
            conv1,
            conv2,
            alpha_norm,
            alpha_dot,
            grid,
            proj,
            conv1_sources: None,
            readout: None,
            threads: 1,
            products: MProducts::Gauss,
        })
    }

    /// Prepares [`GraphAttention::forward_zero_destinations`] and
    /// [`GraphAttention::invariant_zero_destinations`]: a first SO(2) convolution that
    /// reads only the source channels of the messages, and the m = 0 parts of the two
    /// convolutions that the invariant readout needs.
    pub fn prepare_zero_destinations(&mut self) -> Result<()> {
        let conv1 = self.conv1.first_channels(self.cfg.sphere_channels)?;
        // The gated activation replaces the l = 0 row by SiLU(gating) and scales each other
        // row by an invariant: the second convolution's m = 0 rows then come from the first
        // one's m = 0 rows (its l > 0 outputs) and its gating scalars alone. A grid
        // activation mixes every row, so it needs the whole first convolution.
        let conv1_m0 = if self.grid.gated {
            Some(conv1.m0_block(&(1..=self.cfg.lmax).collect::<Vec<_>>())?)
        } else {
            None
        };
        self.readout = Some(InvariantReadout {
            conv1_m0,
            conv2_l0: self.conv2.m0_block(&[0])?,
        });
        self.conv1_sources = Some(conv1);
        Ok(())
    }

    /// [`GraphAttention::forward`] onto `nd` destinations whose features are all zero (the
    /// field heads' queries): the zero half of every message is never built or multiplied.
    pub fn forward_zero_destinations(
        &self,
        x_src: &[f32],
        nd: usize,
        edges: &EdgeSet,
    ) -> Result<Vec<f32>> {
        let k = num_coefficients(self.cfg.lmax);
        match &self.conv1_sources {
            Some(conv1) => self.forward_with(x_src, None, nd, edges, conv1),
            None => {
                let zeros = vec![0.0f32; nd * k * self.cfg.sphere_channels];
                self.forward(x_src, &zeros, edges)
            }
        }
    }

    /// The l = 0 rows of [`GraphAttention::forward_zero_destinations`], `[Nd,
    /// output_channels]`, bit for bit, without the work that only the other rows need: the
    /// output projection keeps degrees apart and the rotation back leaves l = 0 as it is, so
    /// only the second convolution's l = 0, m = 0 outputs are computed, and with the gated
    /// activation only the first convolution's m = 0 block (the m > 0 rows of the edge
    /// frames are never formed). The translation field reads nothing else. Runs on the
    /// caller's thread (the field heads split their queries over threads themselves).
    pub fn invariant_zero_destinations(
        &self,
        x_src: &[f32],
        nd: usize,
        edges: &EdgeSet,
    ) -> Result<Vec<f32>> {
        let (Some(conv1), Some(readout)) = (&self.conv1_sources, &self.readout) else {
            return Err(PolicyError::BadConfig(
                "the attention's invariant readout is not prepared: call \
                 GraphAttention::prepare_zero_destinations first"
                    .into(),
            ));
        };
        let cfg = &self.cfg;
        let k = num_coefficients(cfg.lmax);
        let c = cfg.sphere_channels;
        let (heads, vc) = (cfg.num_heads, cfg.value_channels);
        let hv = heads * vc;
        let ns = self.source_nodes(x_src, edges)?;
        // The aggregated values in the full layout (rows l > 0 stay zero) so that the
        // projection is the one the whole layer applies.
        let mut agg = vec![0.0f32; nd * k * hv];
        for r in destination_chunks(&edges.dst, EDGE_CHUNK) {
            let (src, dst) = (&edges.src[r.clone()], &edges.dst[r.clone()]);
            check_edge_nodes(src, dst, ns, nd)?;
            let wig = (&*edges.wigners, r.clone());
            let attr = edges.attr.slice(r);
            let (v0, mut alpha_in) = match &readout.conv1_m0 {
                Some(m0) => {
                    let out = m0.forward_rotated(wig, (x_src, src), attr)?;
                    readout.gated_values(m0.outputs(), &out, cfg)?
                }
                None => {
                    let (h, extra) = conv1.forward_rotated(
                        wig,
                        c,
                        (x_src, src),
                        None,
                        Some(attr),
                        self.products,
                    )?;
                    let (alpha_in, gating) = split_extra(&extra, cfg);
                    let h = separable_s2_activation(&self.grid, &gating, &h, cfg.hidden_channels)?;
                    // The activated m = 0 rows, l ascending.
                    let nr = self.map.len();
                    let hc = cfg.hidden_channels;
                    let mut rows = Vec::with_capacity(src.len() * (cfg.lmax + 1) * hc);
                    for he in h.chunks_exact(nr * hc) {
                        for l in 0..=cfg.lmax {
                            let p = self.map.position(l, 0);
                            rows.extend_from_slice(&he[p * hc..(p + 1) * hc]);
                        }
                    }
                    (readout.conv2_l0.forward(&rows)?, alpha_in)
                }
            };
            let logit = self.logits(&mut alpha_in, src.len());
            let alpha = grouped_softmax(&logit, dst, nd, heads);
            // As the whole layer: each value times its weight, rotated back (l = 0: times
            // D⁰ = 1), added at its destination in edge order.
            for (e, &d) in dst.iter().enumerate() {
                let out = &mut agg[d * k * hv..d * k * hv + hv];
                for hd in 0..heads {
                    let a = alpha[e * heads + hd];
                    let vs = &v0[e * hv + hd * vc..e * hv + (hd + 1) * vc];
                    for (o, v) in out[hd * vc..(hd + 1) * vc].iter_mut().zip(vs) {
                        *o += v * a;
                    }
                }
            }
        }
        let y = self.proj.forward(&agg)?;
        let co = cfg.output_channels;
        Ok(y.chunks_exact(k * co)
            .flat_map(|row| row[..co].iter().copied())
            .collect())
    }

    /// Attends from `x_src` `[Ns, K, C]` to `x_dst` `[Nd, K, C]` over `edges`; returns
    /// `[Nd, K, output_channels]`.
    pub fn forward(&self, x_src: &[f32], x_dst: &[f32], edges: &EdgeSet) -> Result<Vec<f32>> {
        let k = num_coefficients(self.cfg.lmax);
        let nd = rows_of(
            "attention destination features",
            x_dst.len(),
            k * self.cfg.sphere_channels,
        )?;
        self.forward_with(x_src, Some(x_dst), nd, edges, &self.conv1)
    }

    /// The attention with destination features `x_dst` (None: zero, with `conv1` reading
    /// only the source channels).
    fn forward_with(
        &self,
        x_src: &[f32],
        x_dst: Option<&[f32]>,
        nd: usize,
        edges: &EdgeSet,
        conv1: &So2Conv,
    ) -> Result<Vec<f32>> {
        let cfg = &self.cfg;
        let k = num_coefficients(cfg.lmax);
        let ns = self.source_nodes(x_src, edges)?;
        let row = k * cfg.num_heads * cfg.value_channels;
        let mut agg = vec![0.0f32; nd * row];
        // Whole destination groups at a time keep the buffers small; the softmax is per
        // destination, so this is exact.
        let chunks = destination_chunks(&edges.dst, EDGE_CHUNK);
        let run = |chunks: &[std::ops::Range<usize>], (agg, d0): (&mut [f32], usize)| {
            for r in chunks {
                self.forward_edges(
                    (x_src, x_dst),
                    conv1,
                    (ns, nd),
                    (&edges.src[r.clone()], &edges.dst[r.clone()]),
                    (&*edges.wigners, r.clone()),
                    edges.attr.slice(r.clone()),
                    (&mut *agg, d0),
                )?;
            }
            Ok(())
        };
        if self.threads >= 2 && chunks.len() == 1 && edges.src.len() >= 2 * SPLIT_EDGES_PER_THREAD {
            // One destination group (the rotation head's query: every node attends to it):
            // its edges' messages on the threads, the softmax and the sums in edge order.
            self.forward_edges_split((x_src, x_dst), conv1, (ns, nd), edges, &mut agg)?;
        } else if self.threads < 2 || chunks.len() < 2 {
            run(&chunks, (&mut agg, 0))?;
        } else {
            // More than one chunk means the edges are grouped by ascending destination, so
            // consecutive chunks write consecutive, disjoint rows of `agg`: each chunk gets
            // the rows from its first destination to the next chunk's, and the threads take
            // the chunks one at a time until none is left.
            let mut items = Vec::with_capacity(chunks.len());
            let mut rest = agg.as_mut_slice();
            let mut d0 = 0;
            for (i, r) in chunks.iter().enumerate() {
                let end = match chunks.get(i + 1) {
                    Some(next) => edges.dst[next.start],
                    None => nd,
                };
                if end < d0 || end > nd {
                    return Err(PolicyError::IndexOutOfRange {
                        name: "edge_dst".into(),
                        value: end as i64,
                        len: nd,
                    });
                }
                let (head, tail) = rest.split_at_mut((end - d0) * row);
                items.push((std::slice::from_ref(r), head, d0));
                rest = tail;
                d0 = end;
            }
            crate::parallel::run_dynamic(items, self.threads, |(c, a, d0)| run(c, (a, d0)))
                .into_iter()
                .collect::<Result<()>>()?;
        }
        // The projection is per destination: runs of them on the threads.
        crate::parallel::map_rows(&agg, row, (self.threads, 64), |a| self.proj.forward(a))
    }

    /// The number of source nodes in `x_src` `[Ns, K, C]`, checked, and an error unless the
    /// edges' frames are of this layer's degree.
    fn source_nodes(&self, x_src: &[f32], edges: &EdgeSet) -> Result<usize> {
        let cfg = &self.cfg;
        let k = num_coefficients(cfg.lmax);
        let ns = rows_of(
            "attention source features",
            x_src.len(),
            k * cfg.sphere_channels,
        )?;
        if edges.wigners.lmax != cfg.lmax {
            return Err(PolicyError::UnsupportedDegree {
                lmax: edges.wigners.lmax,
                mmax: cfg.mmax,
                max_supported: cfg.lmax,
            });
        }
        Ok(ns)
    }

    /// Threads of [`GraphAttention::forward`] (1: the caller's only; see [`crate::parallel`]).
    pub fn set_threads(&mut self, threads: usize) {
        self.threads = threads.max(1);
    }

    /// How the SO(2) convolutions compute their m > 0 blocks (Gauss's three products by
    /// default; the plain four are the benchmark's baseline).
    pub fn set_m_products(&mut self, products: MProducts) {
        self.products = products;
    }

    /// The message, attention and aggregation of one chunk of edges (whole destination
    /// groups), added into `agg` `[Nd, K, heads·value]`.
    #[allow(clippy::too_many_arguments)]
    fn forward_edges(
        &self,
        x: (&[f32], Option<&[f32]>),
        conv1: &So2Conv,
        (ns, nd): (usize, usize),
        (src, dst): (&[usize], &[usize]),
        (wigners, range): (&EdgeWigners, std::ops::Range<usize>),
        attr: EdgeFeaturesRef<'_>,
        agg: (&mut [f32], usize),
    ) -> Result<()> {
        let (v, logit) = self.edge_messages(
            x,
            conv1,
            (ns, nd),
            (src, dst),
            (wigners, range.clone()),
            attr,
        )?;
        let alpha = grouped_softmax(&logit, dst, nd, self.cfg.num_heads);
        let back = self.weighted_back(v, &alpha, wigners, range)?;
        self.aggregate(&back, dst, nd, agg)
    }

    /// [`GraphAttention::forward_edges`] of all of `edges` as one chunk, its edges split over
    /// the threads for the per-edge work (messages, logits, the weighted values rotated
    /// back); the softmax and the sums at the destinations see every edge in order, so the
    /// values are those of the one-thread pass.
    fn forward_edges_split(
        &self,
        x: (&[f32], Option<&[f32]>),
        conv1: &So2Conv,
        (ns, nd): (usize, usize),
        edges: &EdgeSet,
        agg: &mut [f32],
    ) -> Result<()> {
        let heads = self.cfg.num_heads;
        let parts = crate::parallel::split_even(edges.src.len(), self.threads);
        let messages = crate::parallel::run_parts(parts.clone(), |r| {
            self.edge_messages(
                x,
                conv1,
                (ns, nd),
                (&edges.src[r.clone()], &edges.dst[r.clone()]),
                (&*edges.wigners, r.clone()),
                edges.attr.slice(r),
            )
        })
        .into_iter()
        .collect::<Result<Vec<_>>>()?;
        let logit: Vec<f32> = messages
            .iter()
            .flat_map(|(_, l)| l.iter().copied())
            .collect();
        let alpha = grouped_softmax(&logit, &edges.dst, nd, heads);
        let items: Vec<_> = parts.iter().cloned().zip(messages).collect();
        let backs = crate::parallel::run_parts(items, |(r, (v, _))| {
            self.weighted_back(v, &alpha[r.start * heads..r.end * heads], &edges.wigners, r)
        });
        for (r, back) in parts.into_iter().zip(backs) {
            self.aggregate(&back?, &edges.dst[r], nd, (&mut *agg, 0))?;
        }
        Ok(())
    }

    /// The per-edge half of the attention for the edges `range` of `wigners` (sources
    /// `src`, destinations `dst`): the values `[E, n_reduced, heads·value]` in the edge
    /// frames and the attention logits `[E, heads]`.
    #[allow(clippy::too_many_arguments)]
    fn edge_messages(
        &self,
        (x_src, x_dst): (&[f32], Option<&[f32]>),
        conv1: &So2Conv,
        (ns, nd): (usize, usize),
        (src, dst): (&[usize], &[usize]),
        (wigners, range): (&EdgeWigners, std::ops::Range<usize>),
        attr: EdgeFeaturesRef<'_>,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        let cfg = &self.cfg;
        let c = cfg.sphere_channels;
        let ne = src.len();
        // Messages concat(x_src[src], x_dst[dst]) along channels (just x_src[src] when the
        // destinations are zero and `conv1` reads only those channels).
        let mc = if x_dst.is_some() { 2 * c } else { c };
        if conv1.cin != mc {
            return Err(PolicyError::ShapeMismatch {
                name: "attention message channels".into(),
                expected: vec![conv1.cin],
                got: vec![mc],
            });
        }
        check_edge_nodes(src, dst, ns, nd)?;
        // The messages are rotated straight from the node features into the convolution's
        // |m| blocks (no gathered copy, no rotated copy).
        let (h, extra) = conv1.forward_rotated(
            (wigners, range),
            c,
            (x_src, src),
            x_dst.map(|x| (x, dst)),
            Some(attr),
            self.products,
        )?;
        let (mut alpha_in, gating) = split_extra(&extra, cfg);
        let h = separable_s2_activation(&self.grid, &gating, &h, cfg.hidden_channels)?;
        let (v, _) = self.conv2.forward_with(&h, None, self.products)?;
        let logit = self.logits(&mut alpha_in, ne);
        Ok((v, logit))
    }

    /// The attention logits `[E, heads]` of the first convolution's logit outputs
    /// `alpha_in` `[E, heads·alpha]` (normalised in place); the softmax over each
    /// destination's edges is the caller's.
    fn logits(&self, alpha_in: &mut [f32], ne: usize) -> Vec<f32> {
        let cfg = &self.cfg;
        self.alpha_norm.apply(alpha_in);
        let heads = cfg.num_heads;
        let ac = cfg.alpha_channels;
        // σ of every input at once, eight at a time, for the smooth leaky ReLU.
        let mut sig = alpha_in[..ne * heads * ac].to_vec();
        crate::vector_exp::sigmoid_in_place(&mut sig);
        let mut logit = vec![0.0f32; ne * heads];
        for e in 0..ne {
            for hd in 0..heads {
                let at = (e * heads + hd) * ac..(e * heads + hd + 1) * ac;
                let w = &self.alpha_dot[hd * ac..(hd + 1) * ac];
                logit[e * heads + hd] = alpha_in[at.clone()]
                    .iter()
                    .zip(&sig[at])
                    .zip(w)
                    .map(|((x, s), y)| smooth_leaky_relu_of(*x, *s, 0.2) * y)
                    .sum();
            }
        }
        logit
    }

    /// Each head's values `v` `[E, n_reduced, heads·value]` weighted by its attention `alpha`
    /// `[E, heads]` and rotated back to the global frame: `[E, K, heads·value]`.
    fn weighted_back(
        &self,
        mut v: Vec<f32>,
        alpha: &[f32],
        wigners: &EdgeWigners,
        range: std::ops::Range<usize>,
    ) -> Result<Vec<f32>> {
        let cfg = &self.cfg;
        let heads = cfg.num_heads;
        let nr = self.map.len();
        let vc = cfg.value_channels;
        let ne = range.len();
        check_len("attention values", v.len(), &[ne, nr, heads * vc])?;
        check_len("attention weights", alpha.len(), &[ne, heads])?;
        for e in 0..ne {
            for r in 0..nr {
                for hd in 0..heads {
                    let a = alpha[e * heads + hd];
                    let base = (e * nr + r) * heads * vc + hd * vc;
                    for x in &mut v[base..base + vc] {
                        *x *= a;
                    }
                }
            }
        }
        wigners.rotate_back_range(range, &self.map, &v, heads * vc)
    }

    /// Adds each edge's rotated-back values `back` `[E, K, heads·value]` into its
    /// destination's row of `agg` (rows from destination `d0` on), in edge order.
    fn aggregate(
        &self,
        back: &[f32],
        dst: &[usize],
        nd: usize,
        (agg, d0): (&mut [f32], usize),
    ) -> Result<()> {
        let cfg = &self.cfg;
        let row = num_coefficients(cfg.lmax) * cfg.num_heads * cfg.value_channels;
        check_len("attention messages", back.len(), &[dst.len(), row])?;
        for (e, &dst_e) in dst.iter().enumerate() {
            let d = dst_e
                .checked_sub(d0)
                .filter(|d| (d + 1) * row <= agg.len())
                .ok_or(PolicyError::IndexOutOfRange {
                    name: "edge_dst of a destination chunk".into(),
                    value: dst_e as i64,
                    len: nd,
                })?;
            for (a, b) in agg[d * row..(d + 1) * row]
                .iter_mut()
                .zip(&back[e * row..(e + 1) * row])
            {
                *a += b;
            }
        }
        Ok(())
    }
}

/// The m = 0 parts of an attention's two convolutions for its invariant readout onto
/// all-zero destinations ([`GraphAttention::invariant_zero_destinations`]).
#[derive(Debug, Clone)]
struct InvariantReadout {
    /// The first convolution's m = 0 block on the source channels, with its extras and its
    /// l > 0 outputs (gated activation only; None with a grid activation).
    conv1_m0: Option<M0Block>,
    /// The second convolution's m = 0 block, its l = 0 outputs only.
    conv2_l0: M0Block,
}

impl InvariantReadout {
    /// From the first convolution's m = 0 outputs `out` `[E, width]` (logit inputs, gating
    /// scalars, then the l > 0 rows): the gated activation of the m = 0 rows (l = 0:
    /// SiLU(gating), l > 0: times σ(gating), as [`crate::grids::gate_activation`]), the
    /// second convolution's l = 0 values `[E, heads·value]`, and the logit inputs.
    fn gated_values(
        &self,
        width: usize,
        out: &[f32],
        cfg: &AttentionConfig,
    ) -> Result<(Vec<f32>, Vec<f32>)> {
        let hc = cfg.hidden_channels;
        let n_alpha = cfg.num_heads * cfg.alpha_channels;
        let ne = rows_of("first convolution's m = 0 outputs", out.len(), width)?;
        check_len(
            "first convolution's m = 0 outputs",
            width,
            &[n_alpha + (cfg.lmax + 1) * hc],
        )?;
        let mut alpha_in = Vec::with_capacity(ne * n_alpha);
        let mut gating = Vec::with_capacity(ne * hc);
        // After the logit inputs each row is [gating | rows l = 1..=lmax]: the m = 0 rows
        // with the gating scalars in the l = 0 slot, which the activation overwrites.
        let mut rows = Vec::with_capacity(ne * (cfg.lmax + 1) * hc);
        for row in out.chunks_exact(width) {
            alpha_in.extend_from_slice(&row[..n_alpha]);
            gating.extend_from_slice(&row[n_alpha..n_alpha + hc]);
            rows.extend_from_slice(&row[n_alpha..]);
        }
        crate::grids::gate_activation_in_place(&mut rows, &gating, &gating, cfg.lmax + 1, hc);
        Ok((self.conv2_l0.forward(&rows)?, alpha_in))
    }
}

/// The first convolution's extra outputs `[E, heads·alpha + hidden]` split into the logit
/// inputs `[E, heads·alpha]` and the gating scalars `[E, hidden]`.
fn split_extra(extra: &[f32], cfg: &AttentionConfig) -> (Vec<f32>, Vec<f32>) {
    let n_alpha = cfg.num_heads * cfg.alpha_channels;
    let n_extra = n_alpha + cfg.hidden_channels;
    let ne = extra.len() / n_extra.max(1);
    let mut alpha_in = Vec::with_capacity(ne * n_alpha);
    let mut gating = Vec::with_capacity(ne * cfg.hidden_channels);
    for row in extra.chunks_exact(n_extra) {
        alpha_in.extend_from_slice(&row[..n_alpha]);
        gating.extend_from_slice(&row[n_alpha..]);
    }
    (alpha_in, gating)
}

/// An error unless every edge's source is below `ns` and its destination below `nd`.
fn check_edge_nodes(src: &[usize], dst: &[usize], ns: usize, nd: usize) -> Result<()> {
    check_len("edge_dst", dst.len(), &[src.len()])?;
    for (&s, &d) in src.iter().zip(dst) {
        if s >= ns || d >= nd {
            return Err(PolicyError::IndexOutOfRange {
                name: "edge_src/edge_dst".into(),
                value: if s >= ns { s as i64 } else { d as i64 },
                len: if s >= ns { ns } else { nd },
            });
        }
    }
    Ok(())
}

/// Edges per thread below which a single destination chunk stays on one thread (at 128, the
/// coarsest U-net level's 480 edges, 32 nodes in one chunk, are split too).
const SPLIT_EDGES_PER_THREAD: usize = 128;

/// Edges per chunk of the attention (whole destination groups are never split).
const EDGE_CHUNK: usize = 512;

/// Ranges of about `chunk` edges that end at destination changes; one range over all edges
/// when the edges are not grouped by destination.
pub fn destination_chunks(dst: &[usize], chunk: usize) -> Vec<std::ops::Range<usize>> {
    if dst.windows(2).any(|w| w[1] < w[0]) || dst.is_empty() {
        return std::iter::once(0..dst.len()).collect();
    }
    let mut out = Vec::new();
    let mut start = 0;
    for e in 1..=dst.len() {
        if e == dst.len() || (e - start >= chunk && dst[e] != dst[e - 1]) {
            out.push(start..e);
            start = e;
        }
    }
    out
}

/// Softmax of `logit` `[E, heads]` over the edges sharing a destination (max subtracted,
/// 1e-16 added to the denominator, as PyG).
pub fn grouped_softmax(logit: &[f32], dst: &[usize], nd: usize, heads: usize) -> Vec<f32> {
    let mut max = vec![f32::NEG_INFINITY; nd * heads];
    for (e, &d) in dst.iter().enumerate() {
        for h in 0..heads {
            let m = &mut max[d * heads + h];
            *m = m.max(logit[e * heads + h]);
        }
    }
    let mut out = vec![0.0f32; logit.len()];
    let mut sum = vec![0.0f32; nd * heads];
    for (e, &d) in dst.iter().enumerate() {
        for h in 0..heads {
            let v = (logit[e * heads + h] - max[d * heads + h]).exp();
            out[e * heads + h] = v;
            sum[d * heads + h] += v;
        }
    }
    for (e, &d) in dst.iter().enumerate() {
        for h in 0..heads {
            out[e * heads + h] /= sum[d * heads + h] + 1e-16;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::predict::PolicyConfig;

    /// The translation field's attention (degree 1) onto zero destinations: its invariant
    /// readout equals the l = 0 rows of the whole layer to the bit, with the gated
    /// activation and with grid activations, for products on the small path (the tiny
    /// widths) and through `matrixmultiply` (every side above 5), over several chunks.
    #[test]
    fn the_invariant_readout_equals_the_whole_layers_l0_rows_bit_for_bit() {
        use crate::grids::S2Resolution;
        use rand::{Rng, SeedableRng};
        for wide in [true, false] {
            let mut cfg = PolicyConfig::tiny();
            if wide {
                cfg.model.field_nn_c = 16;
                cfg.model.attn_hidden_channels = vec![8; 3];
                cfg.model.attn_alpha_channels = vec![8; 3];
                cfg.model.attn_value_channels = vec![8; 3];
            }
            let w = crate::init::random_weights(&cfg.model, &cfg.extra, 9);
            let acfg = cfg.model.heads_config().attention(1, 1);
            let rbf = GaussianRbf::load(&w.scope("field_distance_expansion."), 1.98).unwrap();
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
            let mut point =
                || -> [f32; 3] { [0.0; 3].map(|_: f32| rng.random_range(-0.3f32..0.3)) };
            let nodes: Vec<[f32; 3]> = (0..40).map(|_| point()).collect();
            let queries: Vec<[f32; 3]> = (0..30).map(|_| point()).collect();
            // Every node to every query, grouped by query: 1200 edges, three chunks.
            let (src, dst): (Vec<usize>, Vec<usize>) = (0..queries.len())
                .flat_map(|q| (0..nodes.len()).map(move |n| (n, q)))
                .unzip();
            let calc = WignerCalculator::new(1).unwrap();
            let edges = EdgeSet::new(&calc, 1, &nodes, &queries, src, dst, &rbf).unwrap();
            let (k, c) = (4, acfg.sphere_channels);
            let x: Vec<f32> = (0..nodes.len() * k * c)
                .map(|_| rng.random_range(-1.0f32..1.0))
                .collect();
            for res in [
                S2Resolution::Gated,
                S2Resolution::Reference,
                S2Resolution::Square(8),
            ] {
                let mut ga = GraphAttention::load_with_grid(
                    &w.scope("trans_field_layer.0."),
                    acfg,
                    res.grid(1, 1).unwrap(),
                )
                .unwrap();
                assert!(
                    ga.invariant_zero_destinations(&x, queries.len(), &edges)
                        .is_err(),
                    "not prepared: an error, not a guess"
                );
                ga.prepare_zero_destinations().unwrap();
                let whole = ga
                    .forward_zero_destinations(&x, queries.len(), &edges)
                    .unwrap();
                let want: Vec<f32> = whole
                    .chunks_exact(k * acfg.output_channels)
                    .flat_map(|row| row[..acfg.output_channels].iter().copied())
                    .collect();
                let got = ga
                    .invariant_zero_destinations(&x, queries.len(), &edges)
                    .unwrap();
                assert_eq!(got.len(), queries.len() * acfg.output_channels);
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&got), bits(&want), "{res:?}, wide {wide}");
                assert!(got.iter().any(|v| *v != 0.0));
                // Queries with no edges at all: the projection's bias, as the whole layer.
                let none =
                    EdgeSet::new(&calc, 1, &nodes, &queries, Vec::new(), Vec::new(), &rbf).unwrap();
                let whole = ga.forward_zero_destinations(&x, 3, &none).unwrap();
                let want: Vec<f32> = whole
                    .chunks_exact(k * acfg.output_channels)
                    .flat_map(|row| row[..acfg.output_channels].iter().copied())
                    .collect();
                let got = ga.invariant_zero_destinations(&x, 3, &none).unwrap();
                assert_eq!(bits(&got), bits(&want), "no edges, {res:?}");
                // Source features that are not whole nodes, or fewer nodes than the edges
                // name: typed errors.
                assert!(ga
                    .invariant_zero_destinations(&x[1..], queries.len(), &edges)
                    .is_err());
                assert!(ga
                    .invariant_zero_destinations(&x[k * c..], queries.len(), &edges)
                    .is_err());
            }
        }
    }

    #[test]
    fn an_edge_set_with_another_radial_basis_shares_its_frames() {
        let cfg = PolicyConfig::tiny();
        let w = crate::init::random_weights(&cfg.model, &cfg.extra, 4);
        let mut bases = w
            .keys()
            .into_iter()
            .filter(|k| k.ends_with("distance_expansion.mean") && !k.starts_with("field_"))
            .map(|k| {
                let s = w.scope(k.trim_end_matches("mean"));
                GaussianRbf::load(&s, 0.4).unwrap()
            });
        let (first, second) = (bases.next().unwrap(), bases.next().unwrap());
        let pos: Vec<[f32; 3]> = (0..10)
            .map(|i| {
                let t = i as f32;
                [0.03 * t, (0.7 * t).sin() * 0.1, (1.3 * t).cos() * 0.08]
            })
            .collect();
        let (src, dst): (Vec<usize>, Vec<usize>) = (0..10)
            .flat_map(|d| (0..10).filter(move |&s| s != d).map(move |s| (s, d)))
            .unzip();
        let calc = WignerCalculator::new(cfg.model.lmax).unwrap();
        let lmax = cfg.model.lmax;
        let a = EdgeSet::new(&calc, lmax, &pos, &pos, src.clone(), dst.clone(), &first).unwrap();
        let b = a.with_rbf(&second, 2).unwrap();
        let fresh = EdgeSet::new(&calc, lmax, &pos, &pos, src, dst, &second).unwrap();
        assert!(
            Arc::ptr_eq(&a.wigners, &b.wigners),
            "frames shared, not copied"
        );
        assert_eq!(b.wigners.d, fresh.wigners.d);
        assert_eq!(
            (&b.src, &b.dst, &b.vec, &b.dist),
            (&fresh.src, &fresh.dst, &fresh.vec, &fresh.dist)
        );
        assert_eq!(b.attr, fresh.attr, "the second basis's features");
        assert_ne!(b.attr, a.attr, "two blocks' bases differ");
    }
}
