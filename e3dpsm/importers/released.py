"""Import a checkpoint of the released research code (MayurDeshmukh10/E-3DPSM) into the
`released` variant, key for key.

The released `EgoHPE` holds `event_3d_posenet` (the network) and `kalman_filter`; a
PyTorch Lightning checkpoint of its training module prefixes both with `model.`. Tensors
are mapped by rules, each naming the released keys it consumes and the project keys it
fills, so that "every released key is used, every project key is filled or derived" is a
set comparison, not a hope. Fused tensors are split: the decoder's packed `in_proj` into
q and kv, S5's (real, imaginary) pairs into separate tensors, the Kalman log-variances
[48] into [16, 3]. The Kalman F, B and H must be identities (the element-wise filter
relies on it) and are checked, not stored.

Units: the released network predicts metres and its evaluation multiplies by 1000
(docs/model.md#citations, Units). The `released` variant keeps the heads' weights as they
are and scales their output to millimetres (`pose_unit_mm`), and runs the Kalman filter in
millimetres: the learned log-variances move by ln(1e6) (m^2 -> mm^2) and the filter starts
from P0 = 1e6 mm^2 (the release's identity in m^2). The gain, a ratio of variances, is
unchanged, so the fused pose is exactly the release's x 1000. `import.json` records the
conversion.

Reading never executes code: `torch.load(weights_only=True)`, which admits tensors and plain
containers, plus an allow-list of inert types a Lightning checkpoint pickles
(`LIGHTNING_INERT_GLOBALS`), read as what they are made of. Anything else is refused.
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import torch

from e3dpsm.errors import CheckpointError
from e3dpsm.models.variants import RELEASED_VARIANCE_TO_MM2

Tensors = dict[str, torch.Tensor]
NETWORK_PREFIX = "event_3d_posenet."
KALMAN_PREFIX = "kalman_filter."
KALMAN_IDENTITIES = ("F", "B", "H")
# Lightning pickles its `AttributeDict` (a dict with attribute access) in `hyper_parameters`
# (PyTorch Lightning 2.x: lightning_fabric.utilities.data; 1.x: utilities.parsing). Lightning
# need not be installed: the weights-only unpickler builds each as a plain dict, which runs
# no code and loses nothing a state dict needs.
LIGHTNING_INERT_GLOBALS: tuple[tuple[type, str], ...] = tuple((dict, name) for name in (
    "lightning_fabric.utilities.data.AttributeDict",
    "lightning.fabric.utilities.data.AttributeDict",
    "pytorch_lightning.utilities.parsing.AttributeDict",
    "lightning.pytorch.utilities.parsing.AttributeDict",
))
# Project keys that have no released counterpart, with the value they get and why.
DERIVED = {
    "pose_prior_mm": "zeros: the released heads predict absolute poses, with no prior offset",
}
UNITS = {
    "released": "metres: heads, Kalman filter and camera projection (its evaluation multiplies by 1000)",
    "imported": "millimetres: outputs x1000 (config pose_unit_mm = 1000 scales the heads' metres), "
                "Kalman log Q and log R + ln(1e6) (m^2 -> mm^2), P0 = 1e6 mm^2 (config kalman_p0)",
}


@dataclass(frozen=True)
class Rule:
    """Released keys -> project keys through `convert` (identity for one-to-one renames)."""

    released: tuple[str, ...]
    project: tuple[str, ...]
    convert: Callable[..., tuple[torch.Tensor, ...]] = lambda *t: t


@dataclass
class ImportResult:
    state_dict: Tensors
    mapping: dict[str, list[str]]
    checks: dict[str, Any] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


# -- reading ---------------------------------------------------------------------------------
def read_released_state_dict(path: str | os.PathLike) -> tuple[Tensors, str]:
    """(state dict with the prefixes stripped, what the file was). Network keys are bare
    (`conv1.0.weight`), Kalman keys are `kalman_filter.<name>`."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        with torch.serialization.safe_globals(list(LIGHTNING_INERT_GLOBALS)):
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for foreign, truncated or unsafe files
        globals_named = sorted(set(re.findall(r"GLOBAL ([\w.]+)", str(exc))))
        if globals_named:
            raise CheckpointError(
                f"{path} holds pickled code or objects besides tensors and plain containers "
                f"({', '.join(globals_named)}); nothing was executed. If you trust the file, re-save its "
                "state_dict alone: torch.save(torch.load(CKPT, weights_only=False)['state_dict'], 'plain.pt')"
            ) from exc
        raise CheckpointError(f"{path} is not a readable PyTorch checkpoint ({type(exc).__name__}); "
                              "expected a Lightning .ckpt or a torch.save'd state_dict") from exc
    if isinstance(payload, dict) and isinstance(payload.get("state_dict"), dict):
        raw, kind = payload["state_dict"], "lightning checkpoint"
    elif isinstance(payload, dict) and payload and all(isinstance(v, torch.Tensor) for v in payload.values()):
        raw, kind = payload, "state_dict"
    else:
        raise CheckpointError(f"{path} is neither a Lightning checkpoint (with 'state_dict') nor a plain "
                              "state_dict of tensors")
    bad = sorted(k for k, v in raw.items() if not isinstance(v, torch.Tensor))
    if bad:
        raise CheckpointError(f"{path}: state_dict entries that are not tensors: {bad[:5]}")
    return {_strip(k): v for k, v in raw.items()}, kind


def _strip(key: str) -> str:
    for prefix, keep in ((NETWORK_PREFIX, ""), (KALMAN_PREFIX, KALMAN_PREFIX)):
        at = key.rfind(prefix)
        if at >= 0 and (at == 0 or key[at - 1] == "."):
            return keep + key[at + len(prefix):]
    if key in ("log_process_var", "log_measurement_var", *KALMAN_IDENTITIES):
        return KALMAN_PREFIX + key  # a bare LearnableKalmanFilter state_dict merged in
    return key


# -- the key map ---------------------------------------------------------------------------
_CONV = ("weight", "bias")
_NORM = ("weight", "bias")
_BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")


def _renamed(released: str, project: str, params: tuple[str, ...] = _CONV) -> list[Rule]:
    return [Rule((f"{released}.{n}",), (f"{project}.{n}",)) for n in params]


def _res_block(released: str, project: str, projects_shortcut: bool) -> list[Rule]:
    rules = (_renamed(f"{released}.bn1", f"{project}.norm1", _BN) + _renamed(f"{released}.conv1", f"{project}.conv1")
             + _renamed(f"{released}.bn2", f"{project}.norm2", _BN) + _renamed(f"{released}.conv2", f"{project}.conv2"))
    if projects_shortcut:
        rules += _renamed(f"{released}.shortcut_conv", f"{project}.shortcut")
    return rules


def _split_pair(t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return t[..., 0].contiguous(), t[..., 1].contiguous()


def _lambda(t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    re, im = _split_pair(t)
    # The project parameterises Re(lambda) = -exp(.) (clamped at -1e-4): stable by design.
    return torch.log((-re).clamp_min(1e-4)), im


def _readouts(t: torch.Tensor) -> tuple[torch.Tensor, ...]:
    p = t.shape[1] // 2  # [H, 2P, 2]: forward columns, then backward columns
    return (*_split_pair(t[:, :p]), *_split_pair(t[:, p:]))


def _in_proj(t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    d = t.shape[0] // 3  # packed [q; k; v] rows -> q, [k; v]
    return t[:d].contiguous(), t[d:].contiguous()


def _log_variance_mm2(t: torch.Tensor, joints: int) -> torch.Tensor:
    """Released log-variances [48] in m^2 -> [J, 3] in mm^2 (computed in float64: the shift,
    13.8, is large against the values' float32 spacing)."""
    return (t.double() + math.log(RELEASED_VARIANCE_TO_MM2)).to(t.dtype).reshape(joints, 3)


def released_rules(model: torch.nn.Module) -> list[Rule]:
    """The complete map for a `released`-layout model (its config gives stage and S5 layout)."""
    cfg = model.config
    widths = (cfg.stem_width, *cfg.widths)
    rules = _renamed("conv1.0", "stem.0")
    for i in range(len(cfg.widths)):
        src, dst = f"encoder_backbone.{i}", f"stages.{i}"
        rules += _res_block(f"{src}.0.res_blocks.0", f"{dst}.block1", widths[i] != widths[i + 1])
        rules += _res_block(f"{src}.0.res_blocks.1", f"{dst}.block2", False)
        rules += _renamed(f"{src}.0.pool", f"{dst}.down")
        if cfg.extra_res_block:
            rules += _res_block(f"{src}.1", f"{dst}.block3", False)
        if cfg.deformable:
            tb, att = f"{src}.2.transformer_blocks.0", f"attention.{i}"
            rules += _renamed(f"{src}.2.norm", f"{att}.norm", _NORM) + _renamed(f"{src}.2.proj_in", f"{att}.proj_in")
            rules += _renamed(f"{tb}.norm1", f"{att}.attn_norm", _NORM)
            rules += _renamed(f"{tb}.attn1.value_proj", f"{att}.attn_value_proj")
            rules += _renamed(f"{tb}.attn1.output_proj", f"{att}.attn_output_proj")
            for name in ("sampling_offsets", "attention_weights", "value_proj", "output_proj"):
                rules += _renamed(f"{tb}.attn1.deform_attn.{name}", f"{att}.attn.{name}")
            rules += _renamed(f"{tb}.norm3", f"{att}.ff_norm", _NORM) + _renamed(f"{tb}.geglu.proj", f"{att}.ff.proj_in")
            rules += _renamed(f"{tb}.dense", f"{att}.ff.proj_out") + _renamed(f"{src}.2.proj_out", f"{att}.proj_out")
    for k, stage in enumerate(sorted(cfg.ssm_stages)):  # released: s5_blocks[0] after stage 1, [1] after stage 4
        src, dst = f"s5_blocks.{k}", f"ssm.{stage}"
        rules += _renamed(f"{src}.attn_norm", f"{dst}.norm1", _NORM) + _renamed(f"{src}.ff_norm", f"{dst}.norm2", _NORM)
        rules += [Rule((f"{src}.ff_enc.weight",), (f"{dst}.ff.proj_in.weight",)),
                  Rule((f"{src}.ff_dec.weight",), (f"{dst}.ff.proj_out.weight",))]
        seq, s5 = f"{src}.s5.seq", f"{dst}.s5"
        rules += [
            Rule((f"{seq}.Lambda",), (f"{s5}.log_neg_lambda_re", f"{s5}.lambda_im"), _lambda),
            Rule((f"{seq}.B",), (f"{s5}.b_re", f"{s5}.b_im"), _split_pair),
            Rule((f"{seq}.C",), (f"{s5}.c_re", f"{s5}.c_im", f"{s5}.cb_re", f"{s5}.cb_im"), _readouts),
            Rule((f"{seq}.D",), (f"{s5}.d",)),
            Rule((f"{seq}.log_step",), (f"{s5}.log_step",)),
        ]
    rules.append(Rule(("query_decoder.joint_queries",), ("decoder.queries",)))
    for layer in range(cfg.decoder_layers):
        src, dst = f"query_decoder.transformer_decoder.layers.{layer}", f"decoder.layers.{layer}"
        for theirs, ours in (("self_attn", "self_attn"), ("multihead_attn", "cross_attn")):
            for part in ("weight", "bias"):
                rules.append(Rule((f"{src}.{theirs}.in_proj_{part}",),
                                  (f"{dst}.{ours}.q_proj.{part}", f"{dst}.{ours}.kv_proj.{part}"), _in_proj))
            rules += _renamed(f"{src}.{theirs}.out_proj", f"{dst}.{ours}.out_proj")
        for name in ("linear1", "linear2", "norm1", "norm2", "norm3"):
            rules += _renamed(f"{src}.{name}", f"{dst}.{name}")
    rules += _renamed("pose_embedding.fc.0", "pose_embed.0") + _renamed("pose_embedding.fc.2", "pose_embed.2")
    rules += _renamed("initial_pose_head", "direct_head") + _renamed("delta_head", "delta_head")
    joints = cfg.num_joints
    rules += [
        Rule((f"{KALMAN_PREFIX}log_process_var",), ("fusion.log_q",), lambda t: (_log_variance_mm2(t, joints),)),
        Rule((f"{KALMAN_PREFIX}log_measurement_var",), ("fusion.log_r",), lambda t: (_log_variance_mm2(t, joints),)),
    ]
    return rules


# -- import ------------------------------------------------------------------------------------
def import_released(released: Mapping[str, torch.Tensor], model: torch.nn.Module) -> ImportResult:
    """Map a stripped released state dict onto `model` (a `released`-variant E3DPSM).

    Raises CheckpointError listing missing keys, unexpected keys or wrong shapes.
    """
    rules = released_rules(model)
    target = model.state_dict()
    checked = {f"{KALMAN_PREFIX}{m}" for m in KALMAN_IDENTITIES}
    expected = {k for r in rules for k in r.released}
    missing = sorted(expected - set(released))
    unexpected = sorted(set(released) - expected - checked)
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"{len(missing)} missing key(s): {_listing(missing)}")
        if unexpected:
            parts.append(f"{len(unexpected)} unexpected key(s): {_listing(unexpected)}")
        raise CheckpointError("not a released E-3DPSM checkpoint: " + "; ".join(parts))

    state: Tensors = {}
    mapping: dict[str, list[str]] = {}
    shape_errors = []
    for rule in rules:
        try:
            converted = rule.convert(*(released[k] for k in rule.released))
        except (IndexError, RuntimeError) as exc:
            shape_errors.append(f"{rule.released[0]} {list(released[rule.released[0]].shape)} ({exc})")
            continue
        for key, value in zip(rule.project, converted):
            if tuple(value.shape) != tuple(target[key].shape):
                shape_errors.append(f"{rule.released[0]} {list(released[rule.released[0]].shape)} -> {key} "
                                    f"{list(value.shape)}, expected {list(target[key].shape)}")
            state[key] = value.to(target[key].dtype).clone()
        mapping[" + ".join(rule.released)] = list(rule.project)
    if shape_errors:
        raise CheckpointError(f"{len(shape_errors)} tensor(s) of the wrong shape: {_listing(shape_errors, 3)}")

    checks: dict[str, Any] = {}
    for name in KALMAN_IDENTITIES:
        key = f"{KALMAN_PREFIX}{name}"
        if key in released:
            eye = torch.eye(3 * model.config.num_joints)
            if released[key].shape != eye.shape or not torch.equal(released[key].float(), eye):
                raise CheckpointError(f"{key} is not the {eye.shape[0]}x{eye.shape[0]} identity; the element-wise "
                                      "Kalman filter of this project needs A = B = H = I")
            checks[f"kalman_{name}_identity"] = True
        else:
            checks[f"kalman_{name}_identity"] = "absent"
    for key in DERIVED:
        state[key] = torch.zeros_like(target[key])
    unfilled = sorted(set(target) - set(state))
    if unfilled:  # a rule table out of step with the model: a bug here, not bad input
        raise RuntimeError(f"import rules leave project keys unfilled: {unfilled}")

    warnings = []
    for key in (k for k in released if k.endswith(".s5.seq.Lambda")):
        unstable = int((released[key][..., 0] >= -1e-4).sum())
        if unstable:
            warnings.append(f"{key}: {unstable} mode(s) with Re(lambda) >= -1e-4 clamped to -1e-4 (unbounded "
                            "streams need strictly stable modes); outputs differ from the release there")
    checks.update(
        released_keys=len(released), released_keys_used=len(expected), kalman_identities_checked=sorted(checked & set(released)),
        project_keys=len(target), project_keys_filled=len(target) - len(DERIVED), derived=dict(DERIVED),
        units=dict(UNITS),
        network_parameters=sum(v.numel() for k, v in released.items()
                               if not k.startswith(KALMAN_PREFIX) and _is_parameter(k)),
        kalman_parameters=sum(released[f"{KALMAN_PREFIX}{n}"].numel() for n in ("log_process_var", "log_measurement_var")),
        max_abs_value=max(float(v.float().abs().max()) for v in released.values() if v.numel()),
        finite=all(bool(torch.isfinite(v.float()).all()) for v in released.values()),
    )
    if not checks["finite"]:
        raise CheckpointError("checkpoint holds NaN or infinite values")
    return ImportResult(state, mapping, checks, warnings)


def _is_parameter(key: str) -> bool:
    return not key.endswith(("running_mean", "running_var", "num_batches_tracked"))


def _listing(items: list[str], limit: int = 8) -> str:
    shown = ", ".join(items[:limit])
    return shown + (f", ... ({len(items) - limit} more)" if len(items) > limit else "")

