"""Every switch and number of the model and the data checked by kind and range, in one table per
group of options (option name -> :class:`Switch`, :class:`Number`, :class:`Choice`, :class:`ListOf`
or :class:`Group`) and one checker, :func:`check_options`.

A value of the wrong kind is not what it says: ``'maybe'`` is true to Python (an ``if automask:``
switched it on), a NaN weight compares false with every bound (``truth_weight=nan`` acted as 0), an
infinite one makes every loss non-finite (each step was skipped, then an untrained network was
scored), and a string met a number deep in the loss as a TypeError. So each is refused where its
group is read, before any work, with one line naming the option as the user typed it:
``model.objective.automask: 'maybe' is not a boolean (true or false)``. The entry points check the
configured groups up front (:func:`fisheyedepth.config.check_options`) with the prefix of their
config (``model.``, ``data.datamodule.``); the classes that read them check again with their own
names (``objective.truth_weight``), for a caller without a config.

A table names the options whose kind it knows; the others (a file, a camera name, a string's choices
with their own message) are left to their reader. The synthetic renderer's table,
:data:`fisheyedepth.synthetic.GENERATE_OPTIONS`, lives beside the renderer (its effects and traffic
bound are the renderer's; the renderer imports this module, which imports nothing of the project)."""

from __future__ import annotations

import math
import numbers
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

    @property
    def noun(self) -> str:
        return "a whole number" if self.whole else "a number"

    @property
    def range(self) -> str:
        """What a number of this kind is: ``a finite number >= 0``, ``a number in [0, 1)``."""
        low, high = math.isfinite(self.low), math.isfinite(self.high)
        if low and high:
            left, right = "(" if self.above else "[", ")" if self.below else "]"
            return f"{self.noun} in {left}{_g(self.low)}, {_g(self.high)}{right}"
        noun = self.noun if self.whole else "a finite number"
        if low:
            return f"{noun} {'>' if self.above else '>='} {_g(self.low)}"
        if high:
            return f"{noun} {'<' if self.below else '<='} {_g(self.high)}"
        return noun

    def check(self, name: str, value: Any) -> None:
        if (value is None and self.optional) or (isinstance(value, str) and value in self.words):
            return
        kind = numbers.Integral if self.whole else numbers.Real
        if isinstance(value, bool) or not isinstance(value, kind):
            raise _refuse(name, value, " or ".join((self.noun, *self.words)))
        low = value > self.low if self.above else value >= self.low
        high = value < self.high if self.below else value <= self.high
        if not (math.isfinite(value) and low and high):
            raise _refuse(name, value, self.range, self.note)


@dataclass(frozen=True)
class Choice:
    """One of the names ``choices``."""

    choices: tuple[str, ...]
    note: str = ""

    def check(self, name: str, value: Any) -> None:
        if not (isinstance(value, str) and value in self.choices):
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

__all__ = [
    "DATAMODULE_OPTIONS",
    "MODEL_OPTIONS",
    "OBJECTIVE_OPTIONS",
    "SWITCH",
    "Choice",
    "Group",
    "Kind",
    "ListOf",
    "Number",
    "Switch",
    "check_options",
]
