"""The depth network: a ResNet or EfficientNet-Lite0 encoder, Monodepth2 U-Net decoder, and a head at each
of 4 scales."""

from __future__ import annotations

import operator
import os

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from ..options.memory import check_memory
from .cost_volume import CostVolume, Sources
from .encoders import encoder_channels, make_encoder
from .heads import (
    MultiChannelHead,
    SigmoidHead,
    at_least_float32,
    bin_expectation,
    conv3x3,
    distance_bins,
    distance_to_sigmoid,
    sigmoid_to_distance,
)

DECODER_CHANNELS = (16, 32, 64, 128, 256)  # Monodepth2's, full to 1/16 resolution
SIZE_MULTIPLE = 32  # the encoder halves the image 5 times and the decoder's skips need every level whole


def check_input_size(size, option: str) -> tuple[int, int]:
    """``size`` [W, H] as a tuple if the network can run at it; else a ValueError naming ``option``, the
    value and the nearest sizes it can run at (each side a multiple of :data:`SIZE_MULTIPLE`)."""
    try:
        w, h = (operator.index(v) for v in size)  # whole numbers only
    except (TypeError, ValueError):
        w = h = 0
    if min(w, h) <= 0:
        raise ValueError(f"{option}: {size!r} is not a size [W, H] in pixels")
    if w % SIZE_MULTIPLE == 0 and h % SIZE_MULTIPLE == 0:
        return w, h
    m = SIZE_MULTIPLE
    below = [max(m, v // m * m) for v in (w, h)]
    above = [-(-v // m) * m for v in (w, h)]
    raise ValueError(
        f"{option}: {[w, h]} cannot be the network's input: each side must be a multiple of {m} (the "
        f"encoder halves it 5 times); the nearest that can: {below} or {above}"
    )


def decoder_channels(width: float = 1.0) -> tuple[int, ...]:
    """Monodepth2's decoder channels times ``width`` (at least 4 each): 0.5 is the robot variant's."""
    if not 0 < width <= 4:
        raise ValueError(f"decoder_width: {width!r}, expected a factor in (0, 4] on Monodepth2's channels")
    return tuple(max(4, round(c * width)) for c in DECODER_CHANNELS)


class ConvBlock(nn.Module):
    """3x3 convolution (reflection padded) + ELU (Monodepth2)."""

    def __init__(self, in_ch: int, out_ch: int):
        super().__init__()
        self.conv = conv3x3(in_ch, out_ch)
        self.act = nn.ELU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        return self.act(self.conv(x))


class DepthDecoder(nn.Module):
    """Monodepth2's decoder: per level an up-convolution, nearest 2x upsampling, the skip connection and a
    second convolution; heads read the features at scales 0..3 (full, 1/2, 1/4, 1/8 resolution)."""

    def __init__(
        self,
        encoder_channels: list[int],
        scales: tuple[int, ...] = (0, 1, 2, 3),
        channels: tuple[int, ...] = DECODER_CHANNELS,
    ):
        super().__init__()
        self.scales, self.channels = scales, tuple(channels)
        self.up0, self.up1 = nn.ModuleList(), nn.ModuleList()
        for i in range(4, -1, -1):
            in_ch = encoder_channels[-1] if i == 4 else channels[i + 1]
            self.up0.append(ConvBlock(in_ch, channels[i]))
            skip = encoder_channels[i - 1] if i > 0 else 0
            self.up1.append(ConvBlock(channels[i] + skip, channels[i]))

    def forward(self, features: list[Tensor]) -> dict[int, Tensor]:
        x = features[-1]
        out = {}
        for j, i in enumerate(range(4, -1, -1)):
            x = F.interpolate(self.up0[j](x), scale_factor=2, mode="nearest")
            if i > 0:
                x = torch.cat((x, features[i - 1]), 1)
            x = self.up1[j](x)
            if i in self.scales:
                out[i] = x
        return out


class DepthNet(nn.Module):
    """Image + camera -> Euclidean distance (and normalised disparity): the one path from pixels to metres.

    ``multi_channel=True``: the paper's head (``n_bins`` log-spaced bins, channel attention,
    :func:`bin_expectation`); ``False``: Monodepth2's sigmoid head mapped through its inverse-depth range.
    ``depth_scale`` (per sample, ``paraxial focal / base_focal``) multiplies the distance, so cameras of
    different focal lengths can share one network.
    ``channels_last``: weights and input in NHWC memory order (the same numbers); a speed lever that
    ``scripts/bench/bench_training.py`` measures, slower than NCHW on the 2-core CPU of BENCHMARKS.md.

    - ``forward(image, depth_scale)``: the network itself, every scale (export traces it);
    - :meth:`for_cameras`: the same with each sample's camera (training);
    - :meth:`distance`: any image of a calibrated camera at its own resolution, resized to the
      training size and back (evaluation, prediction).

    ``encoder``: "resnet" (a ResNet of depth ``resnet``; ``weights`` an optional torchvision ImageNet file)
    or "efficientnet_lite0" (ImageNet weights from its installed package); see
    :func:`~fisheyedepth.models.encoders.make_encoder`.
    """

    def __init__(
        self,
        *,
        resnet: int,
        weights: str | os.PathLike | None,
        multi_channel: bool,
        n_bins: int,
        attention: bool,
        min_distance: float,
        max_distance: float,
        scales: tuple[int, ...],
        base_focal: float | None,
        channels_last: bool,
        upsample: str,
        decoder_width: float,
        encoder: str,
        cost_volume: int,
        cost_volume_min: float,
        cost_volume_max: float,
        cost_volume_stride: int,
        cost_volume_fusion: str,
        source_dropout: float,
    ):
        super().__init__()
        self.upsample = upsample  # checked by its setter
        if base_focal is not None and not (isinstance(base_focal, (int, float)) and base_focal > 0):
            raise ValueError(
                f"base_focal={base_focal!r}: expected a focal length in pixels > 0, or None (depth_scale 1); "
                "'auto' is resolved from the training cameras by train.py"
            )
        self.base_focal = None if base_focal is None else float(base_focal)
        self.encoder = make_encoder(encoder, 1, resnet, weights)
        widths = decoder_channels(decoder_width)
        self.multi_channel, self.scales = multi_channel, tuple(scales)  # a config's list too
        self.decoder = DepthDecoder(self.encoder.channels, self.scales, widths)
        self.cost_volume, self.source_dropout = None, float(source_dropout)
        if cost_volume_stride not in VOLUME_STRIDES:
            raise ValueError(f"cost_volume_stride: {cost_volume_stride!r} is not one of {VOLUME_STRIDES}")
        self.volume_level = VOLUME_STRIDES.index(cost_volume_stride)  # the encoder map it joins
        check_network_memory(  # its weights, before they are allocated
            {
                "encoder": encoder,
                "resnet": resnet,
                "multi_channel": multi_channel,
                "n_bins": n_bins,
                "scales": self.scales,
                "decoder_width": decoder_width,
                "cost_volume": cost_volume,
                "cost_volume_stride": cost_volume_stride,
            }  # fmt: skip
        )
        if cost_volume:  # the multi-view network: matches joined to the encoder's features
            self.cost_volume = CostVolume(int(cost_volume), cost_volume_min, cost_volume_max)
            if cost_volume_fusion not in FUSIONS:
                raise ValueError(
                    f"cost_volume_fusion: {cost_volume_fusion!r} is not one of {', '.join(FUSIONS)}"
                )
            self.fusion = cost_volume_fusion
            matched = self.encoder.channels[self.volume_level]
            layers = [
                nn.Conv2d(matched + self.cost_volume.channels, matched, 3, padding=1),
                nn.ReLU(inplace=True),
            ]
            if cost_volume_fusion == "residual":  # a correction of the encoder's map, zero at the start:
                # the deeper (ImageNet) stages first see the features they were trained on
                layers.append(nn.Conv2d(matched, matched, 1))
                nn.init.zeros_(layers[-1].weight)
                nn.init.zeros_(layers[-1].bias)
            self.fuse = nn.Sequential(*layers)
        self.min_distance, self.max_distance = min_distance, max_distance
        bins = distance_bins(n_bins, min_distance, max_distance)
        # Both heads start at the same distance, the binned head's (equal logits: the bins' mean, 26 m
        # for 64 bins over 0.5-150 m), so the head switch changes the head and nothing else. Monodepth2's
        # sigmoid of 0.5 would start at 1 m, where metric poses (about 1 m per frame) warp most pixels
        # far off their match; FFT + RS collapsed to the 0.5 m floor from there in one of two seeds.
        self.initial_distance = float(bins.mean())
        if multi_channel:
            self.heads = nn.ModuleDict(
                {str(s): MultiChannelHead(widths[s], n_bins, attention) for s in scales}
            )
            self.register_buffer("bins", bins, persistent=False)
        else:
            initial = float(
                distance_to_sigmoid(torch.tensor(self.initial_distance), min_distance, max_distance)
            )
            self.heads = nn.ModuleDict({str(s): SigmoidHead(widths[s], initial) for s in scales})
        self.channels_last = channels_last
        if channels_last:
            self.to(memory_format=torch.channels_last)
        # the binned head's softmax expectation; training may swap in a torch.compile'd one (a fused
        # kernel, the same numbers), see FisheyeDepthModule's ``compile_kernels``
        self.expectation = bin_expectation

    @property
    def upsample(self) -> str:
        """How :meth:`distance` brings the network's output to a larger image: "distance" or "logits"."""
        return self._upsample

    @upsample.setter
    def upsample(self, value: str) -> None:
        if value not in UPSAMPLING:
            raise ValueError(f"upsample: {value!r} is not one of {', '.join(UPSAMPLING)}")
        self._upsample = value

    def head_outputs(
        self,
        image: Tensor,
        scales: tuple[int, ...] | None = None,
        cameras=None,
        sources: Sources | None = None,
    ) -> dict[int, Tensor]:
        """The heads' raw outputs (bin logits or sigmoids) ``{scale: [B, C, H/2^s, W/2^s]}`` for
        ``scales`` (default: all; the other heads are skipped). The multi-view network also reads the
        ``cameras`` of the images and their ``sources`` (None: the image alone)."""
        if self.channels_last:
            image = image.contiguous(memory_format=torch.channels_last)
        features = self.decoder(self.encode(image, cameras, sources))
        return {s: self.heads[str(s)](x) for s, x in features.items() if scales is None or s in scales}

    def encode(self, image: Tensor, cameras=None, sources: Sources | None = None) -> list[Tensor]:
        """The encoder's 5 feature maps; with a cost volume, the map at ``cost_volume_stride`` is fused with
        the matching cost of ``sources`` over metric distance before the deeper stages read it."""
        if self.cost_volume is None:
            return self.encoder(image)
        features, x = [], image
        for k in range(5):
            x = self.encoder.stage(k, x)
            if k == self.volume_level:
                fused = self.fuse(torch.cat([x, self.match(x, cameras, sources)], 1))
                x = x + fused if self.fusion == "residual" else fused
            features.append(x)
        return features

    def volume_map(self, images: Tensor) -> Tensor:
        """The encoder's map of ``images`` that the cost volume compares (at ``cost_volume_stride``)."""
        for k in range(self.volume_level + 1):
            images = self.encoder.stage(k, images)
        return images

    def match(self, target: Tensor, cameras, sources: Sources | None) -> Tensor:
        """``[B, D + 1, h, w]`` cost volume of the target's features against the sources' (zeros,
        with nothing seen, without sources). In training each sample's sources are withheld with
        probability ``source_dropout``, so that one image alone still gives a usable map."""
        batch, _, height, width = target.shape
        empty = target.new_zeros(batch, self.cost_volume.channels, height, width)
        if sources is None or sources.images.shape[1] == 0:
            return empty
        if cameras is None:
            raise ValueError("cameras: the multi-view network needs the target cameras with its sources")
        n = sources.images.shape[1]
        flat = sources.images.reshape(batch * n, *sources.images.shape[2:]).to(target.dtype)
        if self.channels_last:
            flat = flat.contiguous(memory_format=torch.channels_last)
        theirs = self.volume_map(flat)
        theirs = theirs.reshape(batch, n, *theirs.shape[1:])
        small = [c.resize(width, height) for c in cameras]
        source_cameras = [[c.resize(width, height) for c in cams] for cams in sources.cameras]
        with torch.autocast(target.device.type, enabled=False):  # geometry in float32
            volume = self.cost_volume(
                at_least_float32(target),
                at_least_float32(theirs),
                sources.poses.float(),
                small,
                source_cameras,
            ).to(target.dtype)
        if self.training and self.source_dropout > 0:
            keep = torch.rand(batch, 1, 1, 1, device=target.device) >= self.source_dropout
            volume = volume * keep.to(volume.dtype)
        return volume

    def forward(
        self,
        image: Tensor,
        depth_scale: Tensor | float = 1.0,
        scales: tuple[int, ...] | None = None,
        cameras=None,
        sources: Sources | None = None,
    ) -> dict[str, dict[int, Tensor]]:
        """Returns ``{"distance": {scale: [B, 1, H/2^s, W/2^s]}, "disp": {...}}`` for ``scales`` (default:
        all; inference needs only scale 0, and skips the other heads)."""
        distance, disp = {}, {}
        for s, y in self.head_outputs(image, scales, cameras, sources).items():
            if self.multi_channel:
                distance[s], disp[s] = self.expectation(
                    y, depth_scale, self.bins, self.min_distance, self.max_distance
                )
            else:
                with torch.autocast(y.device.type, enabled=False):  # float32 under bf16 autocast
                    y = at_least_float32(y)
                    scale = torch.as_tensor(depth_scale, dtype=y.dtype, device=y.device).reshape(-1, 1, 1, 1)
                    distance[s] = sigmoid_to_distance(y, self.min_distance, self.max_distance) * scale
                    disp[s] = y
        return {"distance": distance, "disp": disp}

    def depth_scale(self, cameras) -> Tensor:
        """Per-sample ``paraxial focal / base_focal`` ``[B]`` (1 when ``base_focal`` is unset)."""
        return depth_scale(cameras, self.base_focal)

    def for_cameras(
        self, image: Tensor, cameras, scales: tuple[int, ...] | None = None, sources: Sources | None = None
    ) -> dict[str, dict[int, Tensor]]:
        """:meth:`forward` with the ``depth_scale`` of each sample's camera (images at the cameras' size)."""
        return self(image, self.depth_scale(cameras).to(image), scales, cameras, sources)

    def distance(
        self,
        image: Tensor,
        cameras,
        input_size: tuple[int, int] | None = None,
        sources: Sources | None = None,
    ) -> Tensor:
        """Distance ``[B, 1, H, W]`` (metres) of images ``[B, 3, H, W]`` taken by ``cameras`` (one per image,
        at the images' size). The network runs at ``input_size`` (W, H; default: the images' size) on the
        image and camera resized alike (the ``sources`` of the multi-view network too), and its distance
        is upsampled back in inverse-distance space."""
        H, W = image.shape[-2:]
        if sources is not None and input_size is not None:
            sources = sources.resized(*input_size)
        if self.multi_channel and self.upsample == "logits" and input_size and (W, H) != tuple(input_size):
            return self.upsampled_expectation(*resized(image, cameras, input_size), (H, W), sources)

        def run(images: Tensor, small_cameras) -> Tensor:
            return self.for_cameras(images, small_cameras, scales=(0,), sources=sources)["distance"][0]

        return distance_at_size(run, image, cameras, input_size)

    def upsampled_expectation(
        self, image: Tensor, cameras, size: tuple[int, int], sources: Sources | None = None
    ) -> Tensor:
        """The binned head's scale-0 logits upsampled bilinearly to ``size`` (H, W), then the expectation:
        at an edge between a near and a far surface the interpolated logits keep two peaks and the
        expectation switches between them within a pixel or two, where interpolating distances blends them."""
        logits = self.head_outputs(image, (0,), cameras, sources)[0]
        with torch.autocast(logits.device.type, enabled=False):
            logits = F.interpolate(at_least_float32(logits), size=tuple(size), mode="bilinear")
        scale = self.depth_scale(cameras).to(logits)
        return self.expectation(logits, scale, self.bins, self.min_distance, self.max_distance)[0]


UPSAMPLING = ("distance", "logits")
VOLUME_STRIDES = (2, 4)  # the encoder maps a cost volume can join (levels 0 and 1)
# how the volume joins the encoder's map: "residual" adds a correction that starts at zero (the
# pretrained deeper stages keep their input); "replace" passes the fused map on instead (ManyDepth's)
FUSIONS = ("residual", "replace")


# What a network holds per unit of its size options, in bytes: the bounds of :func:`check_network_memory`.
# A parameter: 4 to run it (float32), 16 to train it (its gradient and Adam's two moments too). A training
# step, measured with one Adam step on float32 64x64 batches of 4 (n_bins 1024 -> 4096: +1.0 GiB;
# cost_volume 1024 -> 4096 with ResNet-18's 64 channels and two sources: +5.5 GiB): per bin and output
# pixel of each scale, BIN_BYTES (the logits, their clamp and exp, and the gradients); per source,
# hypothesis and pixel of the cost volume, VOLUME_BYTES per matched channel and 16 more (the warped
# features, the sampling grid, the costs and their gradients).
RUN_PARAMETER_BYTES, TRAIN_PARAMETER_BYTES = 4, 16
BIN_BYTES = 16
VOLUME_BYTES = 12


def bins_memory(
    n_bins: int, widths, scales, batch: int = 0, size=(0, 0), parameter_bytes: int = RUN_PARAMETER_BYTES
) -> int:
    """Bytes that ``n_bins`` make the binned head hold: ``parameter_bytes * n_bins * sum_s (widths[s] * 9
    + 1)`` (each scale's 3x3 convolution to the logits), and in a training step of ``batch`` images of
    ``size`` (W, H) ``BIN_BYTES * batch * n_bins * sum_s W * H / 4^s`` (the logits at each scale)."""
    weights = parameter_bytes * n_bins * sum(widths[s] * 9 + 1 for s in scales)
    pixels = sum(size[0] * size[1] // 4**s for s in scales)
    return weights + BIN_BYTES * batch * n_bins * pixels


def volume_memory(
    hypotheses: int,
    channels: int,
    batch: int = 0,
    size=(0, 0),
    stride: int = 4,
    sources: int = 0,
    parameter_bytes: int = RUN_PARAMETER_BYTES,
) -> int:
    """Bytes that a cost volume of ``hypotheses`` distances makes the network hold: ``parameter_bytes *
    channels * (channels + hypotheses + 1) * 9`` (the 3x3 convolution that fuses the volume with the
    encoder's map of ``channels``) and 4 per hypothesis (its inverse distance); in a training step of
    ``batch`` images of ``size`` (W, H) with ``sources`` each, ``VOLUME_BYTES * (channels + 16) * batch *
    sources * hypotheses * (W / stride) * (H / stride)`` (each source warped at every hypothesis)."""
    weights = parameter_bytes * channels * (channels + hypotheses + 1) * 9 + 4 * hypotheses
    pixels = (size[0] // stride) * (size[1] // stride)
    return weights + VOLUME_BYTES * (channels + 16) * batch * sources * hypotheses * pixels


def check_network_memory(
    net, prefix: str = "", batch: int = 0, size=(0, 0), sources: int = 0, training: bool = False
) -> None:
    """A ValueError naming ``prefix`` + ``n_bins`` or ``cost_volume`` when the network of the options
    ``net`` (those of :class:`DepthNet`) needs more memory than this machine has
    (:func:`~fisheyedepth.options.memory.check_memory`): its weights (:func:`bins_memory`,
    :func:`volume_memory`), and with ``training`` their gradients and Adam's moments and a step's
    activations on ``batch`` images of ``size`` with ``sources`` source images each."""
    parameter_bytes = TRAIN_PARAMETER_BYTES if training else RUN_PARAMETER_BYTES
    step = f"; a training step of {batch} images of {size[0]}x{size[1]}" if training and batch else ""
    scales = tuple(net["scales"])
    if net["multi_channel"]:
        widths = decoder_channels(net["decoder_width"])
        need = bins_memory(net["n_bins"], widths, scales, batch, size, parameter_bytes)
        what = f"the binned head's logits at {len(scales)} scales{step}"
        check_memory(f"{prefix}n_bins", net["n_bins"], need, what)
    if net["cost_volume"]:
        stride = net["cost_volume_stride"]
        level = VOLUME_STRIDES.index(stride) if stride in VOLUME_STRIDES else 0
        channels = encoder_channels(net["encoder"], net["resnet"])[level]
        need = volume_memory(net["cost_volume"], channels, batch, size, stride, sources, parameter_bytes)
        what = f"distance hypotheses matched on {channels} channels{step}" + (
            f", {sources} sources each" if training and batch else ""
        )
        check_memory(f"{prefix}cost_volume", net["cost_volume"], need, what)


def scale_focal(camera):
    """The focal length (pixels) that sets a camera's ``depth_scale``: the smaller of its paraxial fx and
    fy. ``base_focal: auto`` is the mean of this over the training cameras."""
    return min(camera.paraxial_focal())


def depth_scale(cameras, base_focal: float | None) -> Tensor:
    """Per-camera ``scale_focal / base_focal`` ``[B]``, the factor on the network's distance that lets
    cameras of different focal lengths share one network; 1 for every camera when ``base_focal`` is None."""
    if base_focal is None:
        return torch.ones(len(cameras))
    return torch.tensor([scale_focal(cam) / base_focal for cam in cameras])


def distance_at_size(run, image: Tensor, cameras, input_size: tuple[int, int] | None) -> Tensor:
    """``run(images, cameras) -> distance`` (a network, in any runtime) applied at ``input_size`` (W, H):
    the images area-resized and the cameras resized alike, the distance upsampled back to the images'
    size in inverse-distance space. ``input_size`` None or equal to the images' size: run as they are."""
    H, W = image.shape[-2:]
    if input_size is None or (W, H) == tuple(input_size):
        return run(image, cameras)
    return upsample_inverse(run(*resized(image, cameras, input_size)), (H, W))


def resized(image: Tensor, cameras, size: tuple[int, int]) -> tuple[Tensor, list]:
    """Images area-resized to ``size`` (W, H) and their cameras resized alike."""
    w, h = int(size[0]), int(size[1])
    return F.interpolate(image, size=(h, w), mode="area"), [c.resize(w, h) for c in cameras]


def upsample_inverse(distance: Tensor, size: tuple[int, int]) -> Tensor:
    """Resize ``[B, 1, h, w]`` distance to ``size`` (H, W) bilinearly in inverse-distance space."""
    if distance.shape[-2:] == tuple(size):
        return distance
    inv = F.interpolate(
        1.0 / distance.clamp_min(1e-6), size=tuple(size), mode="bilinear", align_corners=False
    )
    return 1.0 / inv.clamp_min(1e-9)
