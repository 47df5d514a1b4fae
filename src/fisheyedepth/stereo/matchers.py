"""The one interface of a stereo matcher, as the multi-view command, the live rig and the real-world scores
call it: a matcher is an object built from its settings (a frozen dataclass, its parameters named), and
every caller asks it the same four things, never which matcher it holds.

- :meth:`Matcher.maps`: one image's checked and filled distance against one partner image, from the two
  images and the pair's geometry (cameras and ``T_ref_to_partner``);
- :meth:`Matcher.recording`: the matcher's run over a recording's pairings (:mod:`.pairing`), one image
  at a time, each against all its partners (:class:`RecordingMatches`);
- :meth:`Matcher.memory`: bytes its peak needs for one image of a camera, and
  :meth:`Matcher.check_memory` the refusal naming the camera or option when the machine has less;
- :meth:`Matcher.record`: its settings, for a run's summary.

Implementations: :class:`.sgbm.SgbmMatcher` (every pair rectified on the sphere and matched by OpenCV's
semi-global matcher, then fused) and :class:`.sweep.SweepMatcher` (every partner swept at once over
distance hypotheses)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

import numpy as np
import torch

if TYPE_CHECKING:
    from ..cameras.base import CameraModel
    from ..data.layouts import RigLayout
    from .fuse import Fused
    from .pairing import Pairing, Partner
    from .pipeline import Timer

MATCHERS = ("sgbm", "sweep")  # the names of the matchers (Matcher.name), as --matcher takes them


class ImageMaps(NamedTuple):
    """One image's maps against its partners: ``fused`` (None where every partner was left out), the
    partners it holds, and the partners left out because their distances disagree with the others'
    (``"<camera>/<frame>"`` -> why)."""

    fused: Fused | None
    partners: list[Partner]
    disagreeing: dict[str, str]


class RecordingMatches(Protocol):
    """A matcher's run over one recording (:meth:`Matcher.recording`)."""

    def image(self, pairing: Pairing, image: np.ndarray) -> ImageMaps:
        """``pairing``'s image (``image``: as the layout reads it, BGR) against all its partners."""
        ...

    def record(self) -> dict[str, Any]:
        """What the run found beyond each image's maps, for the summary: ``static`` (each camera's share
        of pixels that do not move with the scene), ``pairs`` (each pair's evidence) and
        ``pairs_left_out`` (each pair left out, with why); empty where the matcher judges no pair."""
        ...


class Matcher(Protocol):
    """A stereo matcher (module docstring). ``name``: one of :data:`MATCHERS`; ``min_baseline``: metres
    a camera must have moved for its own earlier or later image to be a partner."""

    name: str
    min_baseline: float

    def maps(
        self,
        image: np.ndarray | torch.Tensor,
        partner_image: np.ndarray | torch.Tensor,
        camera: CameraModel,
        partner_camera: CameraModel,
        T_ref_to_partner: np.ndarray | torch.Tensor,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``image``'s checked and filled distance ``[H, W]`` float32 (0: none) against ``partner_image``.
        Images: ``[1, C, H, W]`` tensors or ``H x W (x 3)`` arrays, RGB."""
        ...

    def recording(self, layout: RigLayout, pairings: list[Pairing], timer: Timer) -> RecordingMatches:
        """The matcher's run over ``pairings`` of ``layout``, its stages' seconds added to ``timer``."""
        ...

    def memory(self, camera: CameraModel) -> float:
        """Bytes the matcher's peak needs for one image of ``camera`` against a partner."""
        ...

    def check_memory(self, name: str, camera: CameraModel, where: str) -> None:
        """Refuse, naming ``where`` (camera ``name`` of a rig file) or the option that sets the need, a
        camera whose :meth:`memory` the machine does not have."""
        ...

    def record(self) -> dict[str, Any]:
        """``{"matcher": name, ...every setting}``."""
        ...


def check_run_memory(layout: RigLayout, matcher: Matcher) -> None:
    """Refuse, before any work, a run whose largest image would need more memory than the machine has
    (:meth:`Matcher.check_memory`), naming the camera (or the option) and both numbers."""
    name, spec = max(layout.cameras.items(), key=lambda kv: kv[1].camera.width * kv[1].camera.height)
    matcher.check_memory(name, spec.camera, f"{layout.root / 'rig.yaml'}: camera {name!r}")
