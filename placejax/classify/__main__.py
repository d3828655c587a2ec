"""``python -m placejax.classify MODEL IMAGE... [--session S] [--json] [--figure out.png]``.

MODEL is a file written by ``PlaceClassifier.save`` or the work directory of a finished
``experiments.cross_season`` run (then ``--session`` names the training session whose classifier to use).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


class UsageError(Exception):
    """A bad argument: the message names it and what was expected."""


def read_image(path: str) -> np.ndarray:
    """uint8 ``(H, W, 3)`` RGB of an image file (anything OpenCV decodes: PNG, JPEG, ...)."""
    import cv2

    p = Path(path)
    if not p.is_file():
        raise UsageError(f"IMAGE {path}: no such file")
    data = np.fromfile(p, np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if img is None:
        raise UsageError(f"IMAGE {path}: not an image file OpenCV can decode (expected PNG, JPEG, BMP, ...)")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def _load_model(model: str, session: str | None):
    from placejax.classify import ArtefactError, PlaceClassifier

    p = Path(model)
    try:
        if p.is_dir():
            if not session:
                raise UsageError(f"MODEL {model} is a run's work directory: pass --session NAME (a training session)")
            return PlaceClassifier.from_run(p, session)
        return PlaceClassifier.load(p)
    except (FileNotFoundError, ArtefactError, KeyError, ValueError) as e:
        msg = e.args[0] if isinstance(e, KeyError) and e.args else str(e)
        raise UsageError(f"MODEL {model}: {msg}") from None


def _text(name: str, rec: dict, grid_n: int) -> str:
    row, col = divmod(rec["class"], grid_n)
    b = rec["cell_bounds_m"]
    verdict = (
        f"UNKNOWN place ({rec['unknown_kind']} score {rec['unknown_score']:.3f} > threshold {rec['threshold']:.3f})"
        if rec["rejected"]
        else "known place"
    )
    return (
        f"{name}: class {rec['class']} (row {row}, col {col}), confidence {rec['confidence']:.3f}, cell centre "
        f"({rec['cell_center_m'][0]:.1f}, {rec['cell_center_m'][1]:.1f}) m, x [{b['x_lo']:.1f}, {b['x_hi']:.1f}] "
        f"y [{b['y_lo']:.1f}, {b['y_hi']:.1f}] m — {verdict} [{rec['branch']}]"
    )


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
    args = parser.parse_args(argv)
    try:
        images = [read_image(p) for p in args.images]
        clf = _load_model(args.model, args.session)
        # Images may differ in size; each is resized to the model's input size, then all run as one batch.
        pairs = zip(args.images, images, strict=True)
        batch = np.stack([clf.prepare(im[None], name=f"IMAGE {p}")[0] for p, im in pairs])
        pred = clf.predict(batch, branch=args.branch)
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    records = pred.records()
    if args.json:
        doc = {
            "model": {"path": args.model, "description": clf.describe(), "train_session": clf.meta["train_session"]},
            "images": [{"image": p, **r} for p, r in zip(args.images, records, strict=True)],
        }
        print(json.dumps(doc, indent=2))
    else:
        print(clf.describe())
        for p, r in zip(args.images, records, strict=True):
            print(_text(p, r, clf.grid.n))
    if args.figure:
        from placejax.classify._figure import draw_predictions

        draw_predictions(clf, images, [Path(p).name for p in args.images], pred, args.figure)
        if not args.json:
            print(f"figure: {args.figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
