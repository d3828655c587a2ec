"""The command's figure: each image beside the workspace map with its predicted cell."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from placejax.io import save_figure


def draw_predictions(
    clf, images: list[np.ndarray], names: list[str], pred, path: str | os.PathLike, *, shapes=None
) -> Path:
    """One row per image: the photograph, then the place grid with the training session's visited cells shaded
    and the predicted cell outlined (green: accepted, red dashed: rejected as an unknown place). Written atomically.
    ``shapes``: each photograph's original ``(H, W)`` for its title, when ``images`` are smaller copies.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    grid = clf.grid
    n = len(images)
    fig, axes = plt.subplots(n, 2, figsize=(10, 4.6 * n), squeeze=False)
    xe, ye = grid.edges
    visited = set(clf.meta.get("visited_classes", []))
    for i, (img, name) in enumerate(zip(images, names, strict=True)):
        ax_img, ax_map = axes[i]
        ax_img.imshow(img)
        ax_img.set_axis_off()
        h, w = img.shape[:2] if shapes is None else shapes[i]
        ax_img.set_title(f"{name} ({h}×{w})", fontsize=12)
        for k in visited:
            x0, x1, y0, y1 = grid.cell_bounds(k)
            # Rows run along x (first coordinate), columns along y; the map draws x horizontally.
            ax_map.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, color="0.88", lw=0))
        for x in xe:
            ax_map.plot([x, x], [ye[0], ye[-1]], color="0.6", lw=0.6)
        for y in ye:
            ax_map.plot([xe[0], xe[-1]], [y, y], color="0.6", lw=0.6)
        if grid.n <= 12:  # the class numbers the text output prints (class = x bin · n + y bin)
            for c in range(grid.num_classes):
                cx0, cx1, cy0, cy1 = grid.cell_bounds(c)
                ax_map.text(
                    (cx0 + cx1) / 2, (cy0 + cy1) / 2, str(c), color="0.45", ha="center", va="center", fontsize=8
                )
        x0, x1, y0, y1 = pred.cell_bounds[i]
        rejected = bool(pred.rejected[i])
        ax_map.add_patch(
            Rectangle(
                (x0, y0),
                x1 - x0,
                y1 - y0,
                fill=False,
                lw=3,
                ls="--" if rejected else "-",
                color="tab:red" if rejected else "tab:green",
            )
        )
        verdict = "unknown place (rejected)" if rejected else "known place"
        ax_map.set_title(
            f"predicted cell {int(pred.label[i])}, confidence {float(pred.confidence[i]):.2f}: {verdict}", fontsize=12
        )
        ax_map.set_xlabel("x (m)", fontsize=11)
        ax_map.set_ylabel("y (m)", fontsize=11)
        ax_map.set_aspect("equal")
        ax_map.tick_params(labelsize=10)
    fig.suptitle(
        f"placejax: predicted place on the {grid.n}×{grid.n} workspace grid (model trained on "
        f"{clf.meta['train_session']}; grey: cells it visited; class = x bin · {grid.n} + y bin)",
        fontsize=13,
    )
    fig.tight_layout()
    path = Path(path)
    save_figure(fig, path, dpi=100)
    plt.close(fig)
    return path
