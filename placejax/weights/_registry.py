"""Named pretrained weights: where they come from, how to check, convert and preprocess for them.

``load(name)`` finds the original PyTorch file (an explicit path, else the cache, else a download through
pooch with a progress bar, checksum check and atomic rename), converts it with the registered converter and
caches the converted Flax variables next to it, keyed by the source file's SHA-256, so later loads skip the
conversion.

Cache layout under ``$PLACEJAX_CACHE`` (default ``~/.cache/placejax``)::

    weights/<original file name>                 the downloaded PyTorch checkpoint, untouched
    converted/<name>-<sha256[:16]>.npz           converted variables ("collection/a/b/leaf" keys)
"""

from __future__ import annotations

import os
import zipfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from flax import traverse_util

from placejax import io
from placejax.models import IMAGENET_MEAN as _IMAGENET_MEAN
from placejax.models import IMAGENET_STD as _IMAGENET_STD
from placejax.weights._convert import convert_depth_anything_v2, convert_midas_small, convert_vgg16
from placejax.weights._torch_checkpoint import read_torch_checkpoint

__all__ = [
    "REGISTRY",
    "Preprocessing",
    "PretrainedWeights",
    "WeightsUnavailableError",
    "cache_dir",
    "fetch",
    "load",
]

Variables = dict[str, Any]
# The float32 constants of placejax.models, as the exact decimals torchvision publishes.
IMAGENET_MEAN = tuple(round(float(v), 6) for v in _IMAGENET_MEAN)
IMAGENET_STD = tuple(round(float(v), 6) for v in _IMAGENET_STD)


class WeightsUnavailableError(RuntimeError):
    """The weights file is neither given, nor cached, nor downloadable (offline, bad checksum, cut
    transfer)."""


@dataclass(frozen=True)
class Preprocessing:
    """What a network expects of its input image.

    Attributes:
        channel_order: ``"RGB"`` or ``"BGR"``.
        scale: multiply uint8 pixels by this first (``1/255`` → [0, 1]).
        mean: per-channel mean subtracted after scaling, in ``channel_order``.
        std: per-channel divisor after subtracting the mean.
        input_size: the size the weights were trained at, ``(H, W)``; see ``resize`` for how images get there.
        resize: a short description of the resize rule (the implementation lives with the model's inference).
    """

    channel_order: str
    scale: float
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    input_size: tuple[int, int]
    resize: str

    def normalise(self, images: np.ndarray) -> np.ndarray:
        """``(..., 3)`` uint8 RGB (or float already in [0, 255]) → float32 network input, same shape."""
        x = np.asarray(images, np.float32)
        if x.shape[-1:] != (3,):
            raise ValueError(f"expected images with 3 channels last, got shape {x.shape}")
        if self.channel_order == "BGR":
            x = x[..., ::-1]
        return (x * np.float32(self.scale) - np.asarray(self.mean, np.float32)) / np.asarray(self.std, np.float32)


@dataclass(frozen=True)
class PretrainedWeights:
    """One entry of the registry.

    Attributes:
        name: registry key.
        url: the official download address.
        filename: file name in the cache's ``weights/`` folder.
        sha256: full SHA-256 of the file when known.
        sha256_prefix: leading hex digits of the SHA-256 when only those are published (torch hub file names
            carry the first 8).
        size_bytes: approximate file size, for messages.
        model_kwargs: keyword arguments of the placejax model the converted variables fit, where one class
            serves several heads (``DepthAnythingV2.from_encoder(**model_kwargs)``); ``None`` for the default.
        converter: state dict → Flax variables.
        preprocessing: the input the weights expect.
        description: one line on what the weights are.
    """

    name: str
    url: str
    filename: str
    converter: Callable[[Mapping[str, np.ndarray]], Variables]
    preprocessing: Preprocessing
    description: str
    sha256: str | None = None
    sha256_prefix: str | None = None
    size_bytes: int | None = None
    model_kwargs: Mapping[str, Any] | None = None

    def check_hash(self, digest: str, source: str) -> None:
        """Raises ``WeightsUnavailableError`` unless ``digest`` (hex SHA-256 of ``source``) is expected."""
        want = self.sha256 or self.sha256_prefix
        if want and not digest.startswith(want.lower()):
            raise WeightsUnavailableError(
                f"{source}: SHA-256 {digest} does not match the expected {want} of {self.name!r} "
                f"({self.url}); "
                "the file is damaged or not the official one"
            )


REGISTRY: dict[str, PretrainedWeights] = {
    "midas_v21_small_256": PretrainedWeights(
        name="midas_v21_small_256",
        url="https://github.com/isl-org/MiDaS/releases/download/v2_1/midas_v21_small_256.pt",
        filename="midas_v21_small_256.pt",
        converter=convert_midas_small,
        preprocessing=Preprocessing(
            "RGB",
            1 / 255,
            IMAGENET_MEAN,
            IMAGENET_STD,
            (256, 256),
            "keep aspect, longer side 256, sides round-half-even to multiples of 32, bicubic "
            "(placejax.depth.preprocess)",
        ),
        description="MiDaS v2.1 small (EfficientNet-Lite3), relative inverse depth; isl-org/MiDaS v2_1",
        # The release publishes no checksum for this file name; ~85.6 MB of float32 tensors (docs/models.md).
        size_bytes=85_600_000,
    ),
    "vgg16_imagenet": PretrainedWeights(
        name="vgg16_imagenet",
        url="https://download.pytorch.org/models/vgg16-397923af.pth",
        filename="vgg16-397923af.pth",
        converter=convert_vgg16,
        preprocessing=Preprocessing(
            "RGB",
            1 / 255,
            IMAGENET_MEAN,
            IMAGENET_STD,
            (224, 224),
            "any size (adaptive 7×7 pooling); 224×224",
        ),
        description="torchvision VGG16 ImageNet-1k classifier (IMAGENET1K_V1), 1000 classes",
        sha256_prefix="397923af",  # torch hub convention: the file name carries the SHA-256's first 8 digits
        size_bytes=553_433_881,
    ),
}
"""Name → :class:`PretrainedWeights` of the official weights ``load`` knows (``registry:NAME`` for ``resolve``)."""

# Depth Anything V2 (DepthAnything/Depth-Anything-V2, README.md and metric_depth/README.md): the official
# preprocessing of depth_anything_v2/dpt.py's image2tensor, the same for the relative and metric models.
_DAV2_PREPROCESSING = Preprocessing(
    "RGB",
    1 / 255,
    IMAGENET_MEAN,
    IMAGENET_STD,
    (518, 518),
    "keep aspect, short side 518, sides rounded to multiples of 14 (up where rounding would go below 518), "
    "bicubic (cv2.INTER_CUBIC); placejax.models.dav2_input_size gives the size",
)
# The publisher gives no checksum for these files: a truncated or altered download is refused by the safe
# reader's structural checks (zip directory, pickle opcodes, storage sizes) and the converter's key-by-key and
# shape-by-shape check, not by a hash. Sizes: 24.8 M float32 parameters (README), ~99.2 MB as torch.save writes
# them (a file of this layout written here measured 99,216,810 bytes).
_DAV2_SMALL_BYTES = 99_200_000
_HF = "https://huggingface.co/depth-anything"
for _name, _repo, _head, _max_depth, _what in (
    ("depth_anything_v2_vits", "Depth-Anything-V2-Small", "relative", None, "relative inverse depth"),
    (
        "depth_anything_v2_metric_vkitti_vits",
        "Depth-Anything-V2-Metric-VKITTI-Small",
        "metric",
        80.0,
        "metric depth in metres up to 80 m, fine-tuned on Virtual KITTI 2 (outdoor, driving)",
    ),
    (
        "depth_anything_v2_metric_hypersim_vits",
        "Depth-Anything-V2-Metric-Hypersim-Small",
        "metric",
        20.0,
        "metric depth in metres up to 20 m, fine-tuned on Hypersim (indoor)",
    ),
):
    _kwargs = {"encoder": "vits", "head": _head, **({"max_depth": _max_depth} if _max_depth else {})}
    REGISTRY[_name] = PretrainedWeights(
        name=_name,
        url=f"{_HF}/{_repo}/resolve/main/{_name}.pth",
        filename=f"{_name}.pth",
        converter=convert_depth_anything_v2,
        preprocessing=_DAV2_PREPROCESSING,
        description=f"Depth Anything V2 Small (DINOv2 ViT-S/14 + DPT, Apache-2.0), {_what}; "
        f"DepthAnythingV2.from_encoder(**model_kwargs)",
        size_bytes=_DAV2_SMALL_BYTES,
        model_kwargs=_kwargs,
    )
del _name, _repo, _head, _max_depth, _what, _kwargs


def cache_dir() -> Path:
    """``$PLACEJAX_CACHE`` if set, else ``~/.cache/placejax`` (created on first write, not here)."""
    env = os.environ.get("PLACEJAX_CACHE")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "placejax"


def _entry(name: str) -> PretrainedWeights:
    try:
        return REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown pretrained weights {name!r}; registered: {sorted(REGISTRY)}") from None


def fetch(name: str, path: str | os.PathLike | None = None, *, timeout_s: float = 60.0) -> Path:
    """Path of the original weights file of ``name``: ``path`` if given, else the cache, else a download.

    Downloads go through pooch into a temporary file in the cache's ``weights/`` folder; the file is checked
    against the registered checksum and only then renamed into place, so an interrupted or corrupt transfer
    leaves nothing behind.

    Raises:
        FileNotFoundError: ``path`` was given but does not exist.
        WeightsUnavailableError: the download failed (offline, cut, checksum mismatch); the message says which
            file to put where.
    """
    entry = _entry(name)
    if path is not None:
        p = Path(path).expanduser()
        if not p.is_file():
            raise FileNotFoundError(f"weights file for {name!r} not found at {p}")
        return p
    target = cache_dir() / "weights" / entry.filename
    if target.is_file():
        return target
    import pooch  # imported lazily: only downloads need it (and requests)
    import requests

    http = pooch.HTTPDownloader(progressbar=True, timeout=timeout_s)

    def download_and_check(url: str, output_file: str, pup: Any) -> None:
        http(url, output_file, pup)
        # Runs on pooch's temporary file: a mismatch raises before the rename, and pooch deletes the temp.
        entry.check_hash(io.file_sha256(Path(output_file)), url)

    try:
        got = pooch.retrieve(
            entry.url,
            known_hash=None,  # checked in download_and_check (full hash or torch-hub prefix)
            fname=entry.filename,
            path=target.parent,
            downloader=download_and_check,
            progressbar=True,
        )
    except (requests.exceptions.RequestException, OSError, WeightsUnavailableError) as err:
        size = f" (~{entry.size_bytes / 1e6:.0f} MB)" if entry.size_bytes else ""
        raise WeightsUnavailableError(
            f"could not download {name!r} from {entry.url}: {err}\n"
            f"Without network access, download {entry.filename}{size} elsewhere and put it at {target} "
            f"(or set PLACEJAX_CACHE, or pass path=...)."
        ) from err
    return Path(got)


def _flatten(tree: Mapping[str, Any]) -> dict[str, np.ndarray]:
    return {k: np.asarray(v) for k, v in traverse_util.flatten_dict(tree, sep="/").items()}


def _unflatten(flat: Mapping[str, np.ndarray]) -> Variables:
    return traverse_util.unflatten_dict(dict(flat), sep="/")


def load(name: str, path: str | os.PathLike | None = None) -> Variables:
    """Flax variables of the registered pretrained weights ``name``.

    Args:
        name: a ``REGISTRY`` key, e.g. ``"midas_v21_small_256"`` or ``"vgg16_imagenet"``.
        path: an explicit PyTorch weights file; default: the cache, downloading on first use.

    Returns:
        ``{"params": ..., ["batch_stats": ...]}`` NumPy float32 trees for the matching placejax model
        (``MidasSmall()`` / ``VGG16(num_classes=1000)``). Its input convention is
        ``REGISTRY[name].preprocessing``.

    Raises:
        WeightsUnavailableError: no file and no download (the message says where to put the file).
        TorchCheckpointError / ValueError: unreadable file, or one that does not match the model.

    Example (downloads ~86 MB on first use)::

        variables = placejax.weights.load("midas_v21_small_256")
        depth = placejax.depth.predict(variables, images)
    """
    entry = _entry(name)
    source = fetch(name, path)
    digest = io.file_sha256(source)
    if path is None:
        entry.check_hash(digest, str(source))  # a cached file could have been replaced since
    converted = cache_dir() / "converted" / f"{name}-{digest[:16]}.npz"
    if converted.is_file():
        try:
            with np.load(converted) as f:
                return _unflatten({k: f[k] for k in f.files})
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile):
            # An unreadable or truncated cache entry (a crash, a full disk, bit rot): rebuild it rather than fail.
            converted.unlink(missing_ok=True)
    variables = entry.converter(read_torch_checkpoint(source))
    io.write_npz(converted, _flatten(variables))
    return variables
