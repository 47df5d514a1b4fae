"""The kinds an option can be (:class:`Switch`, :class:`Number`, :class:`Choice`, :class:`ListOf`,
:class:`Either`, :class:`Group`), each refusing a value of the wrong kind or range with one line naming
the option as the user typed it, and the one checker of a table of them, :func:`check_options`; a plain
choice among names, :func:`one_of`."""

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


# ------------------------------------------------------------------------------------------ the model
WEIGHT = Number(low=0.0)  # a finite number >= 0
POSITIVE = Number(low=0.0, above=True)  # a finite number > 0
COUNT = Number(low=0, whole=True)
OFFSETS = ListOf(Number(whole=True))  # frame offsets, either side of the target


def one_of(field: str, value: str, choices: tuple[str, ...]) -> str:
    """``value`` if it is one of ``choices``, else a ValueError naming the option ``field``."""
    if value not in choices:
        raise ValueError(f"{field}: {value!r} is not one of {', '.join(choices)}")
    return value
