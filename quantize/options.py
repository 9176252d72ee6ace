"""What `e3dpsm quantize` is asked to do: twelve options a newcomer sets, and an advanced group.

`QuantizeOptions` holds what changes the graph or the verdict for most users; `Advanced`
holds the knobs that experiments turn (frames of each stage, rounding, learned ranges).
Both validate themselves, so a bad value is one `ConfigError` line before any work starts.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from e3dpsm.errors import ConfigError
from e3dpsm.budget import TaskBudget
from e3dpsm.utils.isa import ISA_KINDS, detect_isa

MODES: tuple[str, ...] = ("int8", "int8-dynamic", "fp16", "int8-weights")
# The runtimes the budget can be checked on: every trial and the artifact run on each, the worst counting.
CHECK_RUNTIMES: tuple[str, ...] = ("onnxruntime", "openvino")
# What the graph is for: a CPU kind (utils/isa.py; "auto": this host's) or an integer
# accelerator that runs 16-bit activations in integers ("npu"); only there may a node that
# leaves 8 bits take 16-bit activations instead of float (no CPU runtime here has int16 kernels:
# ONNX Runtime and OpenVINO run such a node in float behind its DequantizeLinear).
TARGETS: tuple[str, ...] = ("auto", *ISA_KINDS, "npu")
WEIGHT_ROUNDINGS: tuple[str, ...] = ("nearest", "adaround")
FLOAT_OUTPUT_CHOICES: tuple[str, ...] = ("none", "matmul", "all")
CALIBRATIONS: tuple[str, ...] = ("minmax", "entropy", "percentile", "mse")


@dataclass(frozen=True)
class Advanced:
    """Knobs for experiments; the defaults are the measured best (docs/quantize.md)."""

    holdout_frames: int = 0        # per held-out sequence for the final check (0: all)
    search_frames: int = 0         # per search sequence for each trial of the search (0: all)
    rank_frames: int = 64          # per search sequence for the one-node trials that only rank
    max_trials: int = 24           # prefix probes of the return-to-float search
    weight_rounding: str = "nearest"
    # Compute outputs left float where no quantised op reads them (outputs.py): "matmul"
    # costs ONNX Runtime nothing and lowers the error; "all" (Conv outputs too) is slower there.
    float_outputs: str = "matmul"
    ranges_from_checkpoint: str | None = None  # learned ranges (distill --qat-ranges-only)
    timing_steps: int = 200        # steps the artifact is timed beside fp32 for the verdict
    budget: TaskBudget = field(default_factory=TaskBudget)

    def __post_init__(self) -> None:
        _choice("--weight-rounding", self.weight_rounding, WEIGHT_ROUNDINGS)
        _choice("--float-outputs", self.float_outputs, FLOAT_OUTPUT_CHOICES)
        for name in ("rank_frames", "max_trials", "timing_steps"):
            if getattr(self, name) < 1:
                raise ConfigError(f"--{name.replace('_', '-')} must be at least 1, got {getattr(self, name)}")
        for name in ("holdout_frames", "search_frames"):
            if getattr(self, name) < 0:
                raise ConfigError(f"--{name.replace('_', '-')} must be 0 (all) or more, got {getattr(self, name)}")


@dataclass(frozen=True)
class QuantizeOptions:
    mode: str = "int8"
    exclude: str = "auto"          # auto (full integer, then the fewest nodes back to float) | none | recurrent | names
    target: str = "auto"
    calibration: str = "minmax"
    frames: int = 200              # calibration frames
    split: str = "train"           # calibration frames come from here
    search_split: str = "val"      # the return-to-float search measures here
    holdout_split: str = "test"    # the budget's final check, on frames neither of the others saw
    holdout_data: str | None = None  # another prepared folder for the final check (default: --data)
    runtimes: tuple[str, ...] = ("onnxruntime",)
    threads: int | None = None
    advanced: Advanced = field(default_factory=Advanced)

    def __post_init__(self) -> None:
        _choice("--mode", self.mode, MODES)
        _choice("--target", self.target, TARGETS)
        _choice("--calibration", self.calibration, CALIBRATIONS)
        unknown = [r for r in self.runtimes if r not in CHECK_RUNTIMES]
        if not self.runtimes or unknown:
            raise ConfigError(f"unknown runtime(s) {unknown}; choose from {list(CHECK_RUNTIMES)}")
        if "openvino" in self.runtimes:
            from e3dpsm.runtime.openvino_session import openvino_available

            available, reason = openvino_available()
            if not available:
                raise ConfigError(f"--runtimes openvino: {reason}")
        if self.frames < 16:
            raise ConfigError(f"--frames {self.frames} is too few for calibration; use at least 16")
        if self.target == "npu" and self.mode != "int8":
            raise ConfigError(f"--target npu places 16-bit activations in an INT8 graph; drop it with --mode {self.mode}")
        if self.mode == "int8-weights" and self.exclude not in ("auto", "none"):
            raise ConfigError(f"--exclude {self.exclude} keeps nodes float in an INT8 or FP16 graph; --mode int8-weights "
                              "stores every weight in 8 bits and computes in float: drop --exclude")
        a = self.advanced
        if self.mode != "int8" and (a.weight_rounding != "nearest" or a.ranges_from_checkpoint):
            raise ConfigError(f"--weight-rounding and --ranges-from-checkpoint shape INT8 graphs; drop them with "
                              f"--mode {self.mode}")
        self._check_splits()

    def _check_splits(self) -> None:
        """Calibration, search and the final check on different frames: the budget must hold on
        frames neither the calibration nor the search saw. "all" overlaps every split."""
        named = {"--split": self.split}
        if self.exclude == "auto" and self.mode in ("int8", "fp16"):  # the modes that search
            named["--search-split"] = self.search_split
        if self.holdout_data is None:
            named["--holdout-split"] = self.holdout_split
        values = list(named.values())
        if len(values) > 1 and ("all" in values or len(set(values)) < len(values)):
            given = " and ".join(f"{flag} {value}" for flag, value in named.items())
            raise ConfigError(f"{given} must name different splits of --data (none of them 'all', or the final check "
                              "on --holdout-data): the budget is checked on frames neither calibration nor search saw")

    @property
    def isa(self) -> str:
        """The CPU kind the graph's kernels are chosen for (an NPU's graph: this host's)."""
        return detect_isa().kind if self.target in ("auto", "npu") else self.target

    @property
    def int16(self) -> bool:
        """Whether nodes that leave 8 bits try 16-bit activations before float."""
        return self.target == "npu"

    def to_dict(self) -> dict:
        return {**asdict(self), "runtimes": list(self.runtimes), "isa": self.isa}


def _choice(flag: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ConfigError(f"unknown {flag} {value!r}; choose from {list(choices)}")


def artifact_name(mode: str) -> str:
    return f"step_{mode.replace('-', '_')}.onnx"
