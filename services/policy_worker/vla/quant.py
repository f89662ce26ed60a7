"""Quantization as a per-module plug-in (the paper's quantization runtime).

``quantize_modules(model, ["encoder.prefix_mlp"])`` swaps the ``nn.Linear`` layers inside the
named submodules for W8A8 dynamic int8 ones (weights int8 per tensor, activations quantized per
batch at run time, ``torch.ao.quantization.quantize_dynamic``); everything else stays float. The
default target is stage 1's prefix MLP, the compute-heavy part, as the paper does for pi0.5.
Dynamic int8 kernels are CPU kernels (fbgemm/onednn/qnnpack): on a CUDA model the plug-in
refuses rather than silently moving modules to the CPU.
"""

from __future__ import annotations

import warnings

import torch
from torch import nn

#: Named targets a deployment can ask for (ZETTA_VLA_QUANTIZE=w8a8 or a list of module paths).
PRESETS = {"w8a8": ["encoder.prefix_mlp"], "w8a8-all-linear": ["encoder", "expert"]}


def quantize_modules(model: nn.Module, targets: list[str]) -> list[str]:
    """Quantize the Linear layers under each target path in place; returns the paths done."""
    paths: list[str] = []
    for t in targets:
        t = t.strip()
        if not t:
            continue
        paths.extend(PRESETS.get(t, [t]))
    if any(p.is_cuda for p in model.parameters()):
        raise ValueError("W8A8 dynamic quantization runs on CPU kernels; load the model on the CPU to quantize")
    done = []
    for path in paths:
        parent_path, _, leaf = path.rpartition(".")
        parent = model.get_submodule(parent_path) if parent_path else model
        module = parent.get_submodule(leaf)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            q = torch.ao.quantization.quantize_dynamic(module, {nn.Linear}, dtype=torch.qint8)
        setattr(parent, leaf, q)
        done.append(path)
    return done


def quantized_linear_count(model: nn.Module) -> int:
    from torch.ao.nn.quantized.dynamic import Linear as DynLinear

    return sum(isinstance(m, DynLinear) for m in model.modules())
