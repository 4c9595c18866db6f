#!/usr/bin/env python3
"""EquiformerV2's SO2EquivariantGraphAttention in PyTorch, for `equact bench attention --torch`.

The layer as the reference runs it in eval mode (separable S2 activation, attention
re-normalisation, no shared radial weights), written from its published structure with the
reference's buffers (coefficient orderings, S2 grids, the inverse-rotation rescale) read from
a fixture of the `equact_fixtures` format. The inputs (node features, edges, radial features,
edge-frame Wigner matrices) and parameters come from a problem file; the output is compared
with the problem's `out.y` (our Rust layer's, or the fixture's own reference output).

Prints one JSON object: max abs error against `out.y`, and the median wall time of the
forward pass over --reps runs on --threads CPU threads.

Run by `equact bench attention --torch PYTHON`; alone:
    python3 policy/benches/torch_attention.py --problem policy/tests/fixtures/graph_attention.safetensors
"""

import argparse
import json
import statistics
import time

import torch
from safetensors.torch import load_file


def linear(x, p, name, bias=True):
    y = x @ p[f"{name}.weight"].T
    return y + p[f"{name}.bias"] if bias else y


def layer_norm(x, p, name):
    return torch.nn.functional.layer_norm(
        x, (x.shape[-1],), p[f"{name}.weight"], p[f"{name}.bias"], 1e-5
    )


def radial(x, p, name):
    # Linear -> LayerNorm -> SiLU, twice, then Linear (net.0/1, net.3/4, net.6).
    for i in (0, 3):
        x = torch.nn.functional.silu(layer_norm(linear(x, p, f"{name}.net.{i}"), p, f"{name}.net.{i + 1}"))
    return linear(x, p, f"{name}.net.6")


def so2_conv(x, p, name, b, cout, extra, x_edge):
    """SO2_Convolution on l-primary reduced coefficients x [E, R, cin]; returns (y, extra)."""
    e, _, cin = x.shape
    to_m, m_size = b["to_m"], b["m_size"]
    x = torch.einsum("nac,ba->nbc", x, to_m)  # m-primary order
    rad = radial(x_edge, p, f"{name}.rad_func") if x_edge is not None else None
    n0 = m_size[0]
    x0 = x[:, :n0].reshape(e, -1)
    if rad is not None:
        x0 = x0 * rad[:, : n0 * cin]
    x0 = linear(x0, p, f"{name}.fc_m0")
    x0_extra, x0 = x0[:, :extra], x0[:, extra:]
    out = [x0.reshape(e, -1, cout)]
    off, off_rad = n0, n0 * cin
    for m in range(1, len(m_size)):
        nm = m_size[m]
        xm = x[:, off : off + 2 * nm].reshape(e, 2, -1)
        if rad is not None:
            xm = xm * rad[:, off_rad : off_rad + nm * cin].reshape(e, 1, -1)
        xm = linear(xm, p, f"{name}.so2_m_conv.{m - 1}.fc", bias=False)
        half = xm.shape[2] // 2
        xr, xi = xm[:, :, :half], xm[:, :, half:]
        real = xr[:, 0] - xi[:, 1]
        imag = xr[:, 1] + xi[:, 0]
        out.append(torch.stack([real, imag], dim=1).reshape(e, -1, cout))
        off += 2 * nm
        off_rad += nm * cin
    y = torch.cat(out, dim=1)
    return torch.einsum("nac,ab->nbc", y, to_m), x0_extra  # back to l-primary


def s2_act(gating, x, grid):
    """Separable S2 activation: SiLU of the gating scalars for l = 0, SiLU on the grid else."""
    to_grid, from_grid = grid
    g = torch.einsum("bai,zic->zbac", to_grid, x)
    g = torch.nn.functional.silu(g)
    y = torch.einsum("bai,zbac->zic", from_grid, g)
    return torch.cat([torch.nn.functional.silu(gating).unsqueeze(1), y[:, 1:]], dim=1)


def smooth_leaky_relu(x, a=0.2):
    return (1 + a) / 2 * x + (1 - a) / 2 * x * (2 * torch.sigmoid(x) - 1)


class Attention:
    def __init__(self, params, buffers, cfg):
        self.p = params
        self.cfg = cfg
        red = buffers["buf.mapping_helper.reduced_coef_idx"].long()
        self.reduced = red
        self.mapping = {
            "to_m": buffers["buf.mappingReduced.to_m"],
            "m_size": [int(v) for v in buffers["buf.mappingReduced.m_size"]],
        }
        lmax, mmax = cfg["lmax"], cfg["mmax"]
        tg = buffers[f"buf.SO3_grid.{lmax}.{mmax}.to_grid_mat"]
        fg = buffers[f"buf.SO3_grid.{lmax}.{mmax}.from_grid_mat"]
        # Stored for the reduced coefficients already ([b, a, reduced]).
        self.grid = (tg, fg)
        self.rescale = buffers["buf.mapping_helper.rotate_inv_rescale"]
        self.expand = buffers["buf.proj.expand_index"].long()

    def forward(self, x, src, dst, edge_attr, wigner):
        c, p = self.cfg, self.p
        e = src.shape[0]
        heads, alpha_c, value_c, hidden = c["heads"], c["alpha"], c["value"], c["hidden"]
        msg = torch.cat([x[src], x[dst]], dim=2)
        w = wigner[:, self.reduced, :]
        msg = w @ msg
        n_alpha = heads * alpha_c
        h, extra = so2_conv(msg, p, "so2_conv_1", self.mapping, hidden, n_alpha + hidden, edge_attr)
        h = s2_act(extra[:, n_alpha:], h, self.grid)
        v, _ = so2_conv(h, p, "so2_conv_2", self.mapping, heads * value_c, 0, None)
        a = extra[:, :n_alpha].reshape(e, heads, alpha_c)
        a = smooth_leaky_relu(layer_norm(a, p, "alpha_norm"))
        logit = torch.einsum("bik,ik->bi", a, p["alpha_dot"])
        # Softmax over the edges of each destination (max subtracted, as torch_geometric).
        n = x.shape[0]
        mx = torch.full((n, heads), -torch.inf).scatter_reduce(
            0, dst.unsqueeze(1).expand(-1, heads), logit, "amax", include_self=True
        )
        ex = torch.exp(logit - mx[dst])
        den = torch.zeros(n, heads).index_add_(0, dst, ex)
        alpha = ex / (den[dst] + 1e-16)
        v = v.reshape(e, v.shape[1], heads, value_c) * alpha.reshape(e, 1, heads, 1)
        v = v.reshape(e, v.shape[1], heads * value_c)
        winv = wigner.transpose(1, 2)[:, :, self.reduced] * self.rescale
        back = winv @ v
        agg = torch.zeros(n, back.shape[1], back.shape[2]).index_add_(0, dst, back)
        weight = p["proj.weight"][self.expand]  # [K, out, in]
        y = torch.einsum("bmi,moi->bmo", agg, weight)
        y[:, 0, :] += p["proj.bias"]
        return y


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--problem", required=True, help="safetensors: param.*, in.*, buf.wigner, out.y")
    ap.add_argument(
        "--buffers",
        help="a graph_attention fixture (its buf.* orderings and grids); default: the problem",
    )
    ap.add_argument("--config", help="JSON sizes (heads, alpha, value, hidden, lmax, mmax)")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    prob = load_file(a.problem)
    bufs = load_file(a.buffers) if a.buffers else prob
    if a.config:
        cfg = json.loads(a.config)
    else:
        sidecar = json.load(open(a.problem.rsplit(".", 1)[0] + ".json"))
        k = sidecar["constructor"]
        cfg = {
            "heads": k["num_heads"],
            "alpha": k["attn_alpha_channels"],
            "value": k["attn_value_channels"],
            "hidden": k["hidden_channels"],
            "lmax": k["lmax_list"][0],
            "mmax": k["mmax_list"][0],
        }
    params = {k[len("param.") :]: v for k, v in prob.items() if k.startswith("param.")}
    layer = Attention(params, bufs, cfg)
    args = (
        prob["in.x"],
        prob["in.edge_src"].long(),
        prob["in.edge_dst"].long(),
        prob["in.edge_attr"],
        prob["buf.wigner"],
    )
    times = []
    with torch.inference_mode():
        y = layer.forward(*args)
        for _ in range(a.reps):
            t = time.perf_counter()
            y = layer.forward(*args)
            times.append(time.perf_counter() - t)
    want = prob["out.y"]
    err = (y - want).abs().max().item()
    print(
        json.dumps(
            {
                "torch": torch.__version__,
                "threads": a.threads,
                "edges": int(args[1].shape[0]),
                "max_abs_err": err,
                "max_abs_value": want.abs().max().item(),
                "median_s": statistics.median(times),
                "times_s": times,
            }
        )
    )


if __name__ == "__main__":
    main()
