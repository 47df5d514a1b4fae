"""Every switch and number of the model and the data checked by kind and range, in one table per
group of options (option name -> :class:`Switch`, :class:`Number`, :class:`Choice`, :class:`ListOf`
or :class:`Group`) and one checker, :func:`check_options`.

A value of the wrong kind is not what it says: ``'maybe'`` is true to Python (an ``if automask:``
switched it on), a NaN weight compares false with every bound (``truth_weight=nan`` acted as 0), an
infinite one makes every loss non-finite (each step was skipped, then an untrained network was
scored), and a string met a number deep in the loss as a TypeError. So each is refused where its
group is read, before any work, with one line naming the option as the user typed it:
``model.objective.automask: 'maybe' is not a boolean (true or false)``. The entry points check the
configured groups up front (:func:`fisheyedepth.config.check_config`) with the prefix of their
config (``model.``, ``data.datamodule.``); the classes that read them check again with their own
names (``objective.truth_weight``), for a caller without a config.

The trainer's options (``trainer.*``, :data:`TRAINER_OPTIONS`) are checked by ``train.py``'s plan, with
the options that contradict each other (:func:`fisheyedepth.options.check_combinations`) and those whose
memory exceeds the machine's (:func:`check_memory`: each bound a formula of what the option allocates,
beside its reader: :func:`fisheyedepth.synthetic.spec.check_render_memory`,
:func:`fisheyedepth.models.depth_net.check_network_memory`).

A table names the options whose kind it knows; the others (a file, a camera name, a string's choices
with their own message) are left to their reader. The synthetic renderer's table,
:data:`fisheyedepth.synthetic.GENERATE_OPTIONS`, lives beside the renderer (its effects and traffic
bound are the renderer's; the renderer imports this module, which imports nothing of the project)."""

from __future__ import annotations

import math
import numbers
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol


class Kind(Protocol):
    def check(self, name: str, value: Any) -> None:
        """A ValueError ``<name>: <value> is not <what it must be>`` unless ``value`` is of this kind."""


def _refuse(name: str, value: Any, what: str, note: str = "") -> ValueError:
    return ValueError(f"{name}: {value!r} is not {what}" + (f" ({note})" if note else ""))


@dataclass(frozen=True)
class Switch:
    """``true`` or ``false``, nothing else (not 1, not ``'yes'``)."""

    def check(self, name: str, value: Any) -> None:
        if not isinstance(value, bool):
            raise _refuse(name, value, "a boolean (true or false)")


SWITCH = Switch()


def _g(bound: float) -> str:
    return f"{bound:g}"


@dataclass(frozen=True)
class Number:
    """A finite number (``whole``: an integer) from ``low`` to ``high``, either end left out with
    ``above``/``below``; None where ``optional`` (the option's off switch or its default), and the
    ``words`` it takes besides numbers (``base_focal: auto``). A boolean is not a number."""

    low: float = -math.inf
    high: float = math.inf
    above: bool = False  # low itself is refused
    below: bool = False  # high itself is refused
    whole: bool = False
    optional: bool = False
    words: tuple[str, ...] = ()
    note: str = ""  # why the range, said after it
    also: tuple[float, ...] = ()  # numbers taken outside the range (``max_steps: -1``, no limit)

    @property
    def noun(self) -> str:
        return "a whole number" if self.whole else "a number"

    @property
    def range(self) -> str:
        """What a number of this kind is: ``a finite number >= 0``, ``a number in [0, 1)``."""
        low, high = math.isfinite(self.low), math.isfinite(self.high)
        if low and high:
            left, right = "(" if self.above else "[", ")" if self.below else "]"
            return " or ".join(
                (f"{self.noun} in {left}{_g(self.low)}, {_g(self.high)}{right}", *map(_g, self.also))
            )
        noun = self.noun if self.whole else "a finite number"
        if low:
            text = f"{noun} {'>' if self.above else '>='} {_g(self.low)}"
        elif high:
            text = f"{noun} {'<' if self.below else '<='} {_g(self.high)}"
        else:
            text = noun
        return " or ".join((text, *map(_g, self.also)))

    def check(self, name: str, value: Any) -> None:
        if (value is None and self.optional) or (isinstance(value, str) and value in self.words):
            return
        kind = numbers.Integral if self.whole else numbers.Real
        if isinstance(value, bool) or not isinstance(value, kind):
            raise _refuse(name, value, " or ".join((self.noun, *self.words)))
        low = value > self.low if self.above else value >= self.low
        high = value < self.high if self.below else value <= self.high
        if not (math.isfinite(value) and low and high) and value not in self.also:
            raise _refuse(name, value, self.range, self.note)


@dataclass(frozen=True)
class Choice:
    """One of the names ``choices`` (a whole number stands for its digits where one is a number,
    ``precision: 32``); None where ``optional``."""

    choices: tuple[str, ...]
    note: str = ""
    optional: bool = False

    def check(self, name: str, value: Any) -> None:
        if value is None and self.optional:
            return
        text = str(value) if isinstance(value, int) and not isinstance(value, bool) else value
        if not (isinstance(text, str) and text in self.choices):
            raise _refuse(name, value, f"one of {', '.join(self.choices)}", self.note)


@dataclass(frozen=True)
class ListOf:
    """A list (or tuple) of ``item``s, each named ``<name>[i]``: ``length`` of them where given; None
    where ``optional``; one string alone stands for a list of it where ``single``."""

    item: Kind
    length: int | None = None
    optional: bool = False
    single: bool = False

    def check(self, name: str, value: Any) -> None:
        if value is None and self.optional:
            return
        if self.single and isinstance(value, str):
            value = [value]
        if not isinstance(value, list | tuple):
            raise _refuse(name, value, "a list")
        if self.length is not None and len(value) != self.length:
            raise _refuse(name, value, f"a list of {self.length} values")
        for i, item in enumerate(value):
            self.item.check(f"{name}[{i}]", item)


@dataclass(frozen=True)
class Either:
    """A value of one of ``kinds`` (``fast_dev_run``: a switch or a count of batches), else refused as not
    ``what``."""

    kinds: tuple[Kind, ...]
    what: str
    note: str = ""

    def check(self, name: str, value: Any) -> None:
        for kind in self.kinds:
            try:
                kind.check(name, value)
            except ValueError:
                continue
            return
        raise _refuse(name, value, self.what, self.note)


@dataclass(frozen=True)
class Group:
    """A mapping of options checked against ``table``, each named ``<name>.<option>``; None where
    ``optional`` (the group switched off)."""

    table: Mapping[str, Kind]
    optional: bool = False

    def check(self, name: str, value: Any) -> None:
        if value is None and self.optional:
            return
        if not isinstance(value, Mapping):
            raise _refuse(name, value, f"a mapping of {', '.join(self.table)}")
        check_options(value, self.table, f"{name}.")


def check_options(options: Mapping[str, Any], table: Mapping[str, Kind], prefix: str = "") -> None:
    """A ValueError naming (``prefix`` + option) the first option of ``table`` that ``options`` sets to
    a value not of its kind; options the table does not name are their reader's to check."""
    for key, kind in table.items():
        if key in options:
            kind.check(f"{prefix}{key}", options[key])


# ------------------------------------------------------------------------------------------ memory
def machine_memory() -> int:
    """This machine's physical memory in bytes (``psutil`` where installed, else ``sysconf``)."""
    try:
        import psutil

        return int(psutil.virtual_memory().total)
    except ImportError:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def in_bytes(n: float) -> str:
    """``n`` bytes for a reader: ``512 MiB``, ``15.6 GiB``, ``8.4 TiB``."""
    for unit, scale in (("PiB", 2**50), ("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n:.0f} bytes"


def check_memory(name: str, value: Any, needed: float, what: str) -> None:
    """A ValueError ``<name>: <value> needs <bytes> of memory (<what>); this machine has <bytes>`` when
    ``needed`` bytes, what the option makes a command allocate, exceed this machine's physical memory
    (:func:`machine_memory`): refused at once, not after hours of swapping or by the kernel's OOM killer."""
    total = machine_memory()
    if needed > total:
        have = in_bytes(total)
        raise ValueError(
            f"{name}: {value!r} needs {in_bytes(needed)} of memory ({what}); this machine has {have}"
        )


# ------------------------------------------------------------------------------------------ the model
WEIGHT = Number(low=0.0)  # a finite number >= 0
POSITIVE = Number(low=0.0, above=True)  # a finite number > 0
COUNT = Number(low=0, whole=True)
OFFSETS = ListOf(Number(whole=True))  # frame offsets, either side of the target
NET_OPTIONS: dict[str, Kind] = {  # fisheyedepth.models.DepthNet
    "resnet": Number(low=1, whole=True),
    "multi_channel": SWITCH,
    "n_bins": Number(low=2, whole=True),
    "attention": SWITCH,
    "min_distance": POSITIVE,
    "max_distance": POSITIVE,
    "scales": ListOf(Number(0, 4, whole=True, note="the decoder's 5 levels")),
    "base_focal": Number(low=0.0, above=True, optional=True, words=("auto",)),
    "channels_last": SWITCH,
    "decoder_width": Number(0.0, 4.0, above=True, note="a factor on Monodepth2's channels"),
    "cost_volume": Number(low=0, whole=True, note="distance hypotheses; 0: the monocular network"),
    "cost_volume_min": POSITIVE,
    "cost_volume_max": POSITIVE,
    "cost_volume_stride": Number(2, 4, whole=True, note="2 or 4: the encoder map the volume joins"),
    "cost_volume_fusion": Choice(("residual", "replace")),
    "source_dropout": Number(0.0, 1.0),
}
OBJECTIVE_OPTIONS: dict[str, Kind] = {  # fisheyedepth.losses.objective.SelfSupervisedObjective
    "fisheye_projection": SWITCH,
    "real_scale": SWITCH,
    "source_offsets": OFFSETS,
    "rig_offsets": OFFSETS,
    "automask": SWITCH,
    "rim_margin": Number(whole=True, optional=True),  # the objective names a negative margin itself
    "smoothness": WEIGHT,
    "outliers": Number(0.0, 1.0, below=True, note="the fraction of each image's pixels left out"),
    "truth_weight": WEIGHT,
    "photometric_weight": WEIGHT,
    "pose_translation_scale": Number(low=0.0, above=True, optional=True),
}
OPTIMIZER_OPTIONS: dict[str, Kind] = {"lr": POSITIVE, "weight_decay": WEIGHT}
SCHEDULER_OPTIONS: dict[str, Kind] = {
    "step_size": Number(low=1, whole=True),
    "gamma": POSITIVE,
    "T_max": Number(low=1, whole=True),
    "eta_min": WEIGHT,
}
MODEL_OPTIONS: dict[str, Kind] = {  # fisheyedepth.module.FisheyeDepthModule: its groups and its own
    "net": Group(NET_OPTIONS),
    "objective": Group(OBJECTIVE_OPTIONS),
    "optimizer": Group(OPTIMIZER_OPTIONS),
    "scheduler": Group(SCHEDULER_OPTIONS),
    "eval_cap": ListOf(WEIGHT, length=2),
    "log_images_every": COUNT,
    "compile_kernels": SWITCH,
}

# ------------------------------------------------------------------------------------------ the data
AUGMENT_OPTIONS: dict[str, Kind] = {  # fisheyedepth.data.Augment
    "flip": Number(0.0, 1.0, note="a probability"),
    # colour jitter: factors drawn from 1 +- spread, so a spread above 1 could invert the image
    "brightness": Number(0.0, 1.0),
    "contrast": Number(0.0, 1.0),
    "saturation": Number(0.0, 1.0),
    "hue": Number(0.0, 0.5, note="turns of the chroma plane"),
}
POSE_NOISE_OPTIONS: dict[str, Kind] = {  # fisheyedepth.data.PoseNoise
    "rotation_deg": WEIGHT,
    "translation": WEIGHT,
    "seed": Number(whole=True),
}
DATAMODULE_OPTIONS: dict[str, Kind] = {  # fisheyedepth.data.FisheyeDataModule
    "offsets": OFFSETS,
    "rig_offsets": OFFSETS,
    "min_translation": WEIGHT,
    "max_translation": POSITIVE,
    "augment": Group(AUGMENT_OPTIONS, optional=True),
    "skip_bad_frames": SWITCH,
    "batch_size": Number(low=1, whole=True),
    "num_workers": COUNT,
    "pin_memory": SWITCH,
    "seed": Number(whole=True),
    "pose_noise": Group(POSE_NOISE_OPTIONS, optional=True),
    "lidar_occlusion": Number(low=0.0, optional=True),
    "source_baseline": Number(low=0.0, above=True, optional=True),
    "max_pose_gap": Number(low=0.0, above=True, optional=True),
}

# ------------------------------------------------------------------------------------------ the trainer
# Lightning's precisions (trainer.precision; auto: fisheyedepth.config.resolve_precision)
TRAINING_PRECISIONS = ("auto", "32-true", "32", "bf16-mixed", "bf16-true", "bf16", "16-mixed", "16-true")
TRAINING_PRECISIONS += ("16", "64-true", "64", "transformer-engine", "transformer-engine-float16")
ACCELERATORS = ("auto", "cpu", "cuda", "gpu", "mps")  # auto: CUDA where torch sees a GPU, else the CPU
BATCHES = Either(  # Lightning's limit_*_batches and val_check_interval: a fraction, or a count
    (Number(0.0, 1.0, above=True), Number(low=1, whole=True)),
    "a fraction in (0, 1] or a whole number of batches >= 1",
)
TRAINER_OPTIONS: dict[str, Kind] = {  # lightning.Trainer, as conf/trainer sets it
    "max_epochs": Number(low=1, whole=True, note="-1 would train without end, 0 not at all"),
    "max_steps": Number(low=1, whole=True, also=(-1,), note="-1: no limit but max_epochs"),
    "limit_train_batches": BATCHES,
    "limit_val_batches": Either(
        (BATCHES, Number(0, 0, whole=True)),
        "a fraction in (0, 1] or a whole number of batches >= 0 (0: no validation)",
    ),
    "val_check_interval": Either(
        (Number(0.0, 1.0, above=True, optional=True), Number(low=1, whole=True)), BATCHES.what
    ),
    "check_val_every_n_epoch": Number(low=1, whole=True, optional=True),
    "num_sanity_val_steps": Number(low=-1, whole=True, note="-1: every validation batch"),
    "accumulate_grad_batches": Number(low=1, whole=True),
    "gradient_clip_val": Number(low=0.0, optional=True, note="null or 0: no clipping"),
    "gradient_clip_algorithm": Choice(("norm", "value"), optional=True),
    "log_every_n_steps": Number(low=1, whole=True),
    "precision": Choice(TRAINING_PRECISIONS),
    "accelerator": Choice(ACCELERATORS),
    "devices": Either(
        (Number(low=1, whole=True, also=(-1,), words=("auto",)), ListOf(Number(low=0, whole=True))),
        "a whole number >= 1, -1 (every device), auto or a list of device numbers",
    ),
    "num_nodes": Number(low=1, whole=True),
    "sync_batchnorm": SWITCH,
    "deterministic": Either((SWITCH, Choice(("warn",))), "true, false or warn"),
    "fast_dev_run": Either(
        (SWITCH, Number(low=1, whole=True)), "a boolean or a whole number of batches >= 1"
    ),
    "enable_progress_bar": SWITCH,
}

__all__ = [
    "DATAMODULE_OPTIONS",
    "MODEL_OPTIONS",
    "OBJECTIVE_OPTIONS",
    "SWITCH",
    "TRAINER_OPTIONS",
    "Choice",
    "Either",
    "Group",
    "Kind",
    "ListOf",
    "Number",
    "Switch",
    "check_memory",
    "check_options",
    "in_bytes",
    "machine_memory",
]
