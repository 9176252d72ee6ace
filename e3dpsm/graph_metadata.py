"""The contract between an exported step graph and whoever runs it: the JSON entries in the
ONNX `metadata_props` (see DESIGN.md). Torch-free and onnx-free, so a device with numpy and
onnxruntime alone can read it from `InferenceSession.get_modelmeta()`.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any, Mapping

from e3dpsm.errors import InputError
from e3dpsm.state import StateSpec

METADATA_VERSION = "1"
KEY_VERSION = "e3dpsm.version"
KEY_STATES = "e3dpsm.states"
KEY_INPUTS = "e3dpsm.inputs"
KEY_OUTPUTS = "e3dpsm.outputs"
KEY_CONFIG = "e3dpsm.config"
KEY_JOINTS = "e3dpsm.joints"
KEY_QUANTIZATION = "e3dpsm.quantization"
REQUIRED_KEYS = (KEY_STATES, KEY_INPUTS, KEY_OUTPUTS, KEY_CONFIG, KEY_JOINTS)


class MetadataError(InputError):
    """A graph without (or with broken) e3dpsm metadata."""


@dataclass(frozen=True)
class GraphMetadata:
    states: tuple[StateSpec, ...]
    inputs: dict[str, Any]
    outputs: list[dict[str, Any]]
    config: dict[str, Any]
    joints: list[str]
    quantization: dict[str, Any] | None = None
    extra: dict[str, str] = field(default_factory=dict)

    # -- convenient views ----------------------------------------------------------------
    @property
    def frame_input(self) -> dict[str, Any]:
        return self.inputs["frame"]

    @property
    def window_input(self) -> dict[str, Any]:
        return self.inputs["window"]

    @property
    def frame_hw(self) -> tuple[int, int]:
        shape = self.frame_input["shape"]
        return int(shape[-2]), int(shape[-1])

    @property
    def train_window_ms(self) -> float:
        return float(self.config["train_window_ms"])

    @property
    def output_names(self) -> list[str]:
        return [o["name"] for o in self.outputs]

    # -- (de)serialisation ---------------------------------------------------------------
    def to_props(self) -> dict[str, str]:
        props = {
            KEY_VERSION: METADATA_VERSION,
            KEY_STATES: json.dumps([s.to_metadata() for s in self.states]),
            KEY_INPUTS: json.dumps(self.inputs),
            KEY_OUTPUTS: json.dumps(self.outputs),
            KEY_CONFIG: json.dumps(self.config),
            KEY_JOINTS: json.dumps(self.joints),
        }
        if self.quantization is not None:
            props[KEY_QUANTIZATION] = json.dumps(self.quantization)
        props.update(self.extra)
        return props

    @classmethod
    def from_props(cls, props: Mapping[str, str], source: str = "graph") -> "GraphMetadata":
        missing = [k for k in REQUIRED_KEYS if k not in props]
        if missing:
            raise MetadataError(
                f"{source} has no e3dpsm metadata (missing {', '.join(missing)}); "
                "export it with `e3dpsm export` (or e3dpsm.export.export_step)"
            )
        try:
            states = tuple(StateSpec.from_metadata(e) for e in json.loads(props[KEY_STATES]))
            quant = json.loads(props[KEY_QUANTIZATION]) if KEY_QUANTIZATION in props else None
            extra = {k: v for k, v in props.items() if k not in (*REQUIRED_KEYS, KEY_VERSION, KEY_QUANTIZATION)}
            return cls(
                states=states,
                inputs=json.loads(props[KEY_INPUTS]),
                outputs=json.loads(props[KEY_OUTPUTS]),
                config=json.loads(props[KEY_CONFIG]),
                joints=json.loads(props[KEY_JOINTS]),
                quantization=quant,
                extra=extra,
            )
        except (ValueError, KeyError, TypeError) as exc:
            raise MetadataError(f"{source} carries broken e3dpsm metadata: {exc}") from exc

    @classmethod
    def from_session(cls, session: Any, source: str = "graph") -> "GraphMetadata":
        """From an onnxruntime.InferenceSession."""
        return cls.from_props(session.get_modelmeta().custom_metadata_map, source)

    @classmethod
    def from_onnx(cls, model: Any, source: str = "graph") -> "GraphMetadata":
        """From an onnx.ModelProto."""
        return cls.from_props({p.key: p.value for p in model.metadata_props}, source)

    def write_to(self, model: Any) -> None:
        """Replace an onnx.ModelProto's `metadata_props` with this metadata."""
        del model.metadata_props[:]
        for key, value in self.to_props().items():
            model.metadata_props.add(key=key, value=value)

    def with_quantization(self, info: dict[str, Any]) -> "GraphMetadata":
        return GraphMetadata(self.states, self.inputs, self.outputs, self.config, self.joints, info, dict(self.extra))
