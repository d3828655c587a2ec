"""``python -m placejax.classify MODEL IMAGE... [--session S] [--json] [--figure out.png]``.

MODEL is a file written by ``PlaceClassifier.save`` or the work directory of a finished
``experiments.cross_season`` run (then ``--session`` names the training session whose classifier to use).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from placejax import cli
from placejax.classify import _images
from placejax.classify._images import MAX_IMAGE_PIXELS


class UsageError(Exception):
    """A bad argument: the message names it and what was expected."""


def read_image(path: str, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """uint8 ``(H, W, 3)`` RGB of an image file (PNG, JPEG, BMP, GIF, WebP, TIFF, PNM), at most ``max_pixels``.

    The size is read from the file's header and checked before decoding (``placejax.classify._images``).

    Raises:
        UsageError: no such file, another format, over the pixel or file-size budget, or undecodable.
    """
    try:
        return _images.read_image(path, max_pixels=max_pixels)
    except (FileNotFoundError, _images.ImageError) as e:
        raise UsageError(f"IMAGE {e}") from None


FIGURE_SIDE = 640
"""Longest side of a photograph as the --figure draws it (the classifier reads its own resized copy)."""


def _thumbnail(image: np.ndarray) -> np.ndarray:
    """The photograph at most :data:`FIGURE_SIDE` pixels on its longer side, for the figure."""
    from placejax.data.camera import resize_image

    h, w = image.shape[:2]
    scale = FIGURE_SIDE / max(h, w)
    if scale >= 1:
        return image
    return resize_image(image, (max(1, round(h * scale)), max(1, round(w * scale))))


def _load_model(model: str, session: str | None):
    from placejax.classify import ArtefactError, PlaceClassifier

    p = Path(model)
    try:
        if p.is_dir():
            if not session:
                from placejax.classify.run_layout import run_sessions

                names = " or ".join(run_sessions(p))  # a folder that is no finished run fails here, saying so
                raise UsageError(
                    f"MODEL {model} is a run's work directory, with a classifier per training session: pass "
                    f"--session NAME ({names})"
                )
            return PlaceClassifier.from_run(p, session)
        return PlaceClassifier.load(p)
    except UsageError:
        raise
    except (FileNotFoundError, ArtefactError, KeyError, ValueError, OSError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        raise UsageError(f"MODEL {model}: {msg}") from None
    except Exception as e:  # a damaged run directory (orbax, ...): still bad input, still one line
        raise UsageError(f"MODEL {model}: could not be read ({type(e).__name__}: {e})") from None


def _text(name: str, rec: dict, grid_n: int) -> str:
    ix, iy = divmod(rec["class"], grid_n)  # class = (bin of x) · n + (bin of y), as on the --figure map
    b = rec["cell_bounds_m"]
    if not rec["rejected"]:
        verdict = "known place"
    elif not math.isfinite(rec["unknown_score"]) or not math.isfinite(rec["confidence"]):
        verdict = "UNKNOWN place (the network's outputs are not finite numbers)"
    else:
        verdict = (
            f"UNKNOWN place ({rec['unknown_kind']} score {rec['unknown_score']:.3f} > threshold {rec['threshold']:.3f})"
        )
    return (
        f"{name}: class {rec['class']} (x bin {ix}, y bin {iy} of {grid_n}), confidence {rec['confidence']:.3f}, "
        "cell centre "
        f"({rec['cell_center_m'][0]:.1f}, {rec['cell_center_m'][1]:.1f}) m, x [{b['x_lo']:.1f}, {b['x_hi']:.1f}] "
        f"y [{b['y_lo']:.1f}, {b['y_hi']:.1f}] m — {verdict} [{rec['branch']}]"
    )


@cli.command
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m placejax.classify",
        description=(
            "Classify photographs into the places (grid cells) of a trained placejax model: class, confidence, the "
            "cell in the workspace frame, and whether the image is rejected as an unknown place."
        ),
    )
    parser.add_argument("model", metavar="MODEL", help="classifier file (PlaceClassifier.save) or a run's workdir")
    parser.add_argument("images", metavar="IMAGE", nargs="+", help="image files (PNG, JPEG, ...), RGB")
    parser.add_argument("--session", help="training session, when MODEL is an experiments.cross_season workdir")
    parser.add_argument("--branch", default="fusion", choices=("fusion", "rgb", "hha"), help="which classifier")
    parser.add_argument("--json", action="store_true", help="print one JSON document instead of text")
    parser.add_argument("--figure", metavar="OUT.png", help="also draw each image beside its cell on the map")
    parser.add_argument(
        "--max-pixels",
        type=int,
        default=MAX_IMAGE_PIXELS,
        help=f"refuse images whose header declares more pixels than this (default {MAX_IMAGE_PIXELS})",
    )
    parser.add_argument(cli.TRACEBACK_FLAG, action="store_true", help=cli.TRACEBACK_HELP)
    args = parser.parse_args(argv)
    if args.figure:
        from placejax.io import check_write_target

        check_write_target(args.figure)  # before any work: a device or folder there is refused, never replaced
    try:
        clf = _load_model(args.model, args.session)
        # Images may differ in size; each is resized to the model's input size as soon as it is read (one decoded
        # photograph in memory at a time, whatever its size), then all run as one batch.
        inputs, shown, shapes = [], [], []
        for p in args.images:
            im = read_image(p, args.max_pixels)
            inputs.append(clf.prepare(im[None], name=f"IMAGE {p}")[0])
            shapes.append(im.shape[:2])
            if args.figure:
                shown.append(_thumbnail(im))
            del im
        batch = np.stack(inputs)
    except UsageError as e:
        # One line, whatever the input: messages may quote file content.
        print(f"error: {' '.join(str(e).split())}"[:2000], file=sys.stderr)
        return 2
    pred = clf.predict(batch, branch=args.branch)
    records = pred.records()
    if args.json:
        doc = {
            "model": {
                "path": args.model,
                "description": clf.describe(),
                "train_session": clf.meta["train_session"],
                "unknown": {k: clf.meta["unknown"][k] for k in ("score", "threshold", "target_frr")},
            },
            "images": [{"image": p, **r} for p, r in zip(args.images, records, strict=True)],
        }
        print(json.dumps(doc, indent=2))
    else:
        print(clf.describe())
        for p, r in zip(args.images, records, strict=True):
            print(_text(p, r, clf.grid.n))
    if args.figure:
        from placejax.classify._figure import draw_predictions

        draw_predictions(clf, shown, [Path(p).name for p in args.images], pred, args.figure, shapes=shapes)
        if not args.json:
            print(f"figure: {args.figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
