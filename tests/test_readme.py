"""README.md and docs/*.md as a test: every ```python block runs as written, every bash block names real modules
and options, every relative link resolves.

Snippets run offline (a ``sitecustomize`` makes every socket fail), as on a fresh machine without a network.
A Python block whose first line is a ``# not run: <why>`` comment is a fragment (it needs a finished run folder or
the real dataset) and is only compiled; every other block runs. Each Python block runs in its own interpreter (a
fresh namespace, the working directory a temporary folder) with
``PLACEJAX_CACHE`` pointing at a temporary cache that holds a MiDaS v2.1 small file in the official format (random
values, written by ``torch_refs/make_random_official_weights.py``), so nothing is downloaded. Blocks that read
``NCLT_ROOT`` run twice: on a tiny fake NCLT tree in the official layout and without it (the SimCampus branch).
Bash blocks run the full experiment, so they are only checked: every ``python -m`` module must exist, and
``experiments.cross_season``'s presets and ``key=value`` overrides must be ones its config knows.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
PAGES = [README, *sorted((REPO / "docs").glob("*.md"))]
WEIGHTS_READMES = sorted(REPO.glob("placejax/*/weights/README.md"))
_FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.MULTILINE | re.DOTALL)
_NOT_RUN = "# not run:"


def _blocks(lang: str, pages: list[Path] = PAGES) -> list[str]:
    return [body for page in pages for kind, body in _FENCE.findall(page.read_text()) if kind == lang]


# Pages whose Python blocks are one worked example, run in order by their own test (which names the page).
RUN_ELSEWHERE = {"own-data.md": "test_folder.py"}
_HERE = [p for p in PAGES if p.name not in RUN_ELSEWHERE]
PYTHON_BLOCKS = [b for b in _blocks("python", _HERE) if not b.startswith(_NOT_RUN)]
FRAGMENTS = [b for b in _blocks("python", _HERE) if b.startswith(_NOT_RUN)]
BASH_BLOCKS = _blocks("bash")


def _first_line(code: str) -> str:
    return next((line for line in code.splitlines() if line and not line.startswith(("import", "from"))), "")


@pytest.fixture(scope="module")
def readme_env(tmp_path_factory, midas_recipe_npz) -> dict[str, str]:
    """Environment of the snippets: a pre-filled weights cache and a fake NCLT tree."""
    tmp = tmp_path_factory.mktemp("readme")
    generated = tmp / "generated"
    script = Path(__file__).parent / "torch_refs" / "make_random_official_weights.py"
    fixture = midas_recipe_npz
    # VGG width 1/16: the VGG16 file is a by-product here (a few MB); the tour does not load ImageNet weights.
    subprocess.run([sys.executable, str(script), str(generated), str(fixture), "0.0625"], check=True)
    cache = tmp / "cache"
    (cache / "weights").mkdir(parents=True)
    # The registry looks for the official file name in $PLACEJAX_CACHE/weights/ (no checksum is published for it).
    (generated / "midas_random.pt").rename(cache / "weights" / "midas_v21_small_256.pt")

    sys.path.insert(0, str(Path(__file__).parent))
    from fake_nclt import make_fake_nclt

    nclt = make_fake_nclt(tmp / "nclt", ["2012-01-22", "2012-03-31"], n_frames=40, stored_hw=(40, 32))
    # No network in the snippets: every socket a snippet opens fails at once, as on a machine offline (the README's
    # tour must run so; MiDaS's weights are the pre-filled cache's, as after their one download).
    offline = tmp / "offline"
    offline.mkdir()
    (offline / "sitecustomize.py").write_text(
        "import socket\n"
        "def _refuse(*args, **kwargs):\n"
        "    raise OSError('network disabled by tests/test_readme.py')\n"
        "socket.socket.connect = _refuse\n"
        "socket.create_connection = _refuse\n"
        "socket.getaddrinfo = _refuse\n"
    )
    env = dict(os.environ)
    env.update(
        PLACEJAX_CACHE=str(cache),
        NCLT_ROOT=str(nclt.root),
        PYTHONPATH=os.pathsep.join([str(offline), str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep),
        # Share compiled programs with the rest of the suite (only ever saves time).
        JAX_COMPILATION_CACHE_DIR=os.environ.get("PLACEJAX_TEST_JAX_CACHE", "/tmp/placejax-test-jax-cache"),
    )
    env.pop("XLA_FLAGS", None)  # the snippets run as a user would: one CPU device
    return env


def _run(code: str, env: dict[str, str], cwd: Path) -> None:
    done = subprocess.run([sys.executable, "-c", code], env=env, cwd=cwd, capture_output=True, text=True)
    assert done.returncode == 0, f"README block failed:\n{code}\n--- stderr ---\n{done.stderr[-4000:]}"


def test_readme_has_python_blocks():
    assert len(_blocks("python", [README])) >= 1
    assert len(PYTHON_BLOCKS) >= 3
    assert BASH_BLOCKS
    # A fragment must say why it is not run, and still be valid Python.
    for code in FRAGMENTS:
        assert len(code.splitlines()[0]) > len(_NOT_RUN) + 3, code
        compile(code, "<fragment>", "exec")
    # A page left to another test is run there: that test reads the page.
    for page, test in RUN_ELSEWHERE.items():
        assert f"docs/{page}" in (Path(__file__).parent / test).read_text() or not (REPO / "docs" / page).exists()


@pytest.mark.slow  # the README's tour end to end: the shipped networks on real frames, compiled
@pytest.mark.parametrize("code", PYTHON_BLOCKS, ids=[_first_line(c)[:40] for c in PYTHON_BLOCKS])
def test_python_block_runs(code, readme_env, tmp_path):
    _run(code, readme_env, tmp_path)
    if "NCLT_ROOT" in code:
        without = {k: v for k, v in readme_env.items() if k != "NCLT_ROOT"}
        _run(code, without, tmp_path)


def _commands(block: str) -> list[list[str]]:
    """Shell words of every ``python -m ...`` command in a bash block (comments and ``&&`` chains split)."""
    out = []
    for line in block.splitlines():
        line = line.split(" #", 1)[0]
        for part in line.split("&&"):
            words = shlex.split(part)
            if len(words) >= 3 and words[0] in ("python", "python3") and words[1] == "-m":
                out.append(words[2:])
    return out


def test_bash_blocks_name_existing_modules_and_options():
    from experiments.cross_season import config

    commands = [c for block in BASH_BLOCKS for c in _commands(block)]
    assert any(c[0] == "experiments.cross_season" for c in commands)
    for module, *args in commands:
        if module in ("venv", "pip", "pytest"):
            continue
        # Placeholders such as [--preset default|smoke|full] describe a usage line, not a command to run.
        assert importlib.util.find_spec(module) is not None, f"README runs python -m {module}, which does not exist"
        if module != "experiments.cross_season":
            continue
        preset = args[args.index("--preset") + 1] if "--preset" in args else "default"
        assert preset in config.PRESETS, f"README uses unknown preset {preset!r}"
        known = config.leaf_keys(config.get_config(preset))
        for arg in args:
            if "=" in arg and not arg.startswith("-"):
                assert arg.split("=", 1)[0] in known, f"README passes unknown config key {arg!r}"


_LINK = re.compile(r"\]\(([^)#\s]+)(?:#([^)\s]*))?\)")


def _anchors(page: Path) -> set[str]:
    """GitHub's anchors of a Markdown page's headings: lower case, punctuation dropped, spaces as hyphens."""
    return {
        re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
        for h in re.findall(r"^#+ (.+)$", page.read_text(), re.MULTILINE)
    }


def test_readme_links_exist():
    """Every relative link or image of the README, the docs pages and the weights READMEs is in the repository,
    every ``docs/*.md`` the README names exists, and the README and the docs index link every docs page."""
    for page in [*PAGES, *WEIGHTS_READMES]:
        for target, anchor in _LINK.findall(page.read_text()):
            if "://" not in target:
                assert (page.parent / target).exists(), f"{page.relative_to(REPO)} links to missing {target}"
                if anchor and target.endswith(".md"):
                    where = page.relative_to(REPO)
                    assert anchor in _anchors(page.parent / target), f"{where}: no #{anchor} in {target}"
    for page in re.findall(r"`(docs/[\w/.-]+\.md)`", README.read_text()):
        assert (REPO / page).is_file(), f"README names missing {page}"
    index = (REPO / "docs" / "index.md").read_text()
    for page in sorted((REPO / "docs").glob("*.md")):
        assert f"](docs/{page.name})" in README.read_text(), f"README does not link docs/{page.name}"
        if page.name != "index.md":
            assert f"]({page.name})" in index, f"docs/index.md does not link {page.name}"


def test_help_shows_every_presets_values():
    """``python -m experiments.cross_season --help`` gives each key's value in every preset, not only the default's."""
    from experiments.cross_season import config, help_epilog

    text = help_epilog()
    for key in config.leaf_keys(config.get_config("default")):
        if key == "preset":
            continue
        block = text.split(f"\n  {key}\n", 1)[1].split("\n", 1)[0]
        for name in config.PRESETS:
            node = config.get_config(name)
            for part in key.split("."):
                node = node[part]
            assert f"{name}={node!r}" in block, (key, name, block)


@pytest.mark.slow
def test_the_test_command_keeps_a_group_on_one_worker(tmp_path):
    """The README's ``--dist loadgroup`` sends every test of an ``xdist_group`` to one worker, so a module fixture
    (a smoke run of minutes) is built once. pytest 9.2 with pytest-xdist 3.8 broke this silently (xdist renames
    ``item._nodeid``, which pytest 9.2 no longer reads): both workers built each smoke run."""
    (tmp_path / "test_grouped.py").write_text(
        "import os, time, pytest\n"
        "pytestmark = pytest.mark.xdist_group('one')\n"
        "@pytest.mark.parametrize('i', range(6))\n"
        "def test_worker(i):\n"
        "    time.sleep(0.2)\n"
        "    print('WORKER', os.environ['PYTEST_XDIST_WORKER'])\n"
    )
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "-n",
            "2",
            "--dist",
            "loadgroup",
            "-rA",
            "-p",
            "no:cacheprovider",
            "test_grouped.py",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stdout + out.stderr
    workers = re.findall(r"^WORKER (gw\d+)$", out.stdout, re.MULTILINE)
    assert len(workers) == 6, out.stdout
    assert len(set(workers)) == 1, out.stdout


RECORD = REPO / "docs" / "cross_season" / "results.json"


def test_the_readme_quotes_the_committed_record_of_its_default_run():
    """Every row of the README's table, its headline time and memory, its ceilings and baselines, and its route and
    unseen-place figures equal the committed record of the run (docs/cross_season/results.json), rounded as
    printed: a number there changes only with the record that backs it."""
    from experiments.cross_season import duration

    rec = json.loads(RECORD.read_text())
    text = README.read_text()
    assert rec["preset"] == "default"
    assert rec["record"]["command"]
    assert rec["record"]["commit"]
    pct = lambda x: f"{100 * x:.1f}"
    acc = lambda r, m, sd: f"{pct(r[m])} ± {pct(sd)}"

    def gain(delta: float, iv: dict) -> str:
        return f"{100 * delta:+.1f} [{100 * iv['lo']:+.1f}, {100 * iv['hi']:+.1f}]" + (
            "*" if iv["excludes_zero"] else ""
        )

    rows = [line for line in text.splitlines() if re.match(r"^\| (WI|SP|SU|AU|\*\*mean\*\*) \|", line)]
    assert len(rows) == 13

    def columns(r: dict, sd: dict, iv: dict) -> list[str]:
        """Ours, RGB-Net, its gain, HHA-Net, its gain, Avg, MLP (paper) as the README prints them."""
        return [
            acc(r, "ours", sd["ours"]),
            acc(r, "rgb_net", sd["rgb_net"]),
            gain(r["ours"] - r["rgb_net"], iv["rgb_net"]),
            acc(r, "hha_net", sd["hha_net"]),
            gain(r["ours"] - r["hha_net"], iv["hha_net"]),
            acc(r, "average", sd["average"]),
            acc(r, "mlp", sd["mlp"]),
        ]

    methods = ("ours", "rgb_net", "hha_net", "average", "mlp")
    for p, row in zip(rec["pairs"], rows[:12], strict=True):
        cells = [c.strip() for c in row.strip("|").split("|")]
        sd = {k: p[f"{k}_sd"] for k in methods}
        iv = {k: p[f"gain_vs_{k}"] for k in ("rgb_net", "hha_net")}
        assert cells[:9] == [p["train"], p["test"], *columns(p, sd, iv)], (p["train"], p["test"])
    m, g = rec["mean"], rec["gains"]
    cells = [c.strip() for c in rows[12].strip("|").split("|")]
    iv = {k: g[f"ours_vs_{k}"] for k in ("rgb_net", "hha_net")}
    assert cells[2:9] == columns(m, rec["mean_sd_over_seeds"], iv)
    flat = " ".join(text.split())
    assert rec["config"]["mlp"]["fusion"] == "pool"
    assert f"log p = {rec['config']['mlp']['pool_weight']:g} · log p(RGB-Net)" in flat
    a, b = g["ours_vs_average"], g["ours_vs_mlp"]
    assert (
        f"beats averaging the two nets' softmax by {gain(a['gain'], a).rstrip('*')} and the paper's MLP by "
        f"{gain(b['gain'], b).rstrip('*')}"
    ) in flat
    assert a["excludes_zero"]
    assert b["excludes_zero"]
    assert f"+{100 * g['ours_vs_rgb_net']['gain']:.1f}; the paper" in flat
    significant = sum(p["gain_vs_hha_net"]["excludes_zero"] for p in rec["pairs"])
    assert f"HHA alone (+{100 * g['ours_vs_hha_net']['gain']:.1f}, significantly on {significant} of 12 pairs" in flat
    assert all(p["ours"] > p["hha_net"] and p["ours"] > p["rgb_net"] for p in rec["pairs"])
    assert f"**{duration(rec['timings_s']['total'])}, peak RSS {rec['peak_rss_mib']['total'] / 1024:.2f} GiB**" in flat
    c = rec["ceilings_and_baselines"]
    assert (
        f"seen classes {pct(c['seen_class_fraction'])}, seen class with a heading within ±45° "
        f"{pct(c['heading_ceiling'])}, 1-NN on 12 × 12 RGB thumbnails {pct(c['nn_rgb'])}, on gradient thumbnails "
        f"{pct(c['nn_gradient'])}, on 16 × 16 HHA thumbnails of this run's depth {pct(c['nn_hha'])}, of rendered "
        f"depth {pct(c['nn_hha_true'])}"
    ) in flat
    r, rg, route = rec["route"]["mean"], rec["route"]["gains"], rec["route"]
    f, q = rg["ours_route_vs_ours"], rg["seq_match_vs_ours"]
    assert (
        f"Ours {pct(m['ours'])} → {pct(r['ours_route'])} % with the filter ({gain(f['gain'], f).rstrip('*')}), "
        f"{pct(r['ours_route_lag'])} % with a lag of {route['lag_frames']} frames ({route['lag_m']:.0f} m), "
        f"{pct(r['seq_match'])} % with sequence matching ({gain(q['gain'], q).rstrip('*')})"
    ) in flat
    assert all(p[c] > p["ours"] for p in rec["pairs"] for c in ("ours_route", "ours_route_lag", "seq_match"))
    assert f"RGB-Net {pct(m['rgb_net'])} → {pct(r['rgb_net_route'])} % with the filter" in flat
    u, k = route["unknown_mean"], rec["unknown"]["mean"]
    assert (
        f"{u['unknown_window_auroc']:.2f} for the route's score, the distance to the nearest training frame averaged "
        f"over {route['sequence']['distance_window']} frames ({100 * u['unknown_window_rejected_seen']:.0f} % of "
        f"seen, {100 * u['unknown_window_rejected_unseen']:.0f} % of unseen frames rejected), "
        f"{u['unknown_route_auroc']:.2f} for the filter's unknown state, {k['unknown_knn1_auroc']:.2f} for the "
        "single-frame distance"
    ) in flat


def test_the_readmes_ceiling_figures_are_the_ablations_record():
    """The rendered-depth ceiling as the README prints it (HHA-Net and Ours on rendered depth, Ours' gain over that
    HHA-Net, the MLP's figure and what the pseudo depth costs) is the committed record of the run with the ceiling
    columns (docs/cross_season/ablations/results.json), whose other columns are the default run's record to the bit."""
    rec = json.loads((REPO / "docs" / "cross_season" / "ablations" / "results.json").read_text())
    base = json.loads(RECORD.read_text())
    flat = " ".join(README.read_text().split())
    m, g = rec["mean"], rec["gains"]["ours_rendered_vs_hha_net_rendered"]
    pct = lambda x: f"{100 * x:.1f}"
    assert (
        f"HHA-Net reaches {pct(m['hha_net_rendered'])} % and Ours {pct(m['ours_rendered'])} %, above it by "
        f"{100 * g['gain']:+.1f} [{100 * g['lo']:+.1f}, {100 * g['hi']:+.1f}], where the MLP falls below it "
        f"({pct(m['mlp_rendered'])} %)"
    ) in flat
    assert g["excludes_zero"]
    assert (
        f"the pseudo depth costs HHA-Net {pct(m['hha_net_rendered'] - m['hha_net'])} points and Ours "
        f"{pct(m['ours_rendered'] - m['ours'])}"
    ) in flat
    for p, q in zip(base["pairs"], rec["pairs"], strict=True):
        for k in ("ours", "rgb_net", "hha_net", "average", "mlp"):
            assert p[f"{k}_per_seed"] == q[f"{k}_per_seed"], (p["train"], p["test"], k)


def test_the_readmes_hha_rows_are_the_benchmarks_record():
    """The HHA rows of the benchmark table, figure for figure, from the committed record of the run they quote."""
    rec = json.loads((REPO / "docs" / "benchmarks" / "hha_speed.json").read_text())
    rows = {(r["size"], r["impl"].startswith("numpy"), r["batch"]): r for r in rec["rows"]}
    lines = [line for line in README.read_text().splitlines() if line.startswith("| HHA encoder")]
    assert len(lines) == 2
    small, large = lines
    r = rows[("256x256", False, 32)]
    numpy_small = rows[("256x256", True, 1)]
    assert f"{r['ms_per_image']:.2f} ms/image ({r['images_per_s']:.0f} images/s)" in small
    assert (
        f"encoder {r['this_images_per_s']:,.0f} against the previous encoder's {r['baseline_images_per_s']:.0f}"
        in small
    )
    assert f"{r['baseline_over_this']:.2f}×" in small
    assert f"{r['speedup']:.0f}× slower" in small
    assert numpy_small["impl"] == "numpy float64 (baseline)"
    b8, b1 = rows[("480x640", False, 8)], rows[("480x640", False, 1)]
    numpy_large = rows[("480x640", True, 1)]
    assert f"{b8['ms_per_image']:.2f} / {b1['ms_per_image']:.1f} ms/image" in large
    assert f"({b8['images_per_s']:.0f} / {b1['images_per_s']:.0f} images/s)" in large
    assert f"encoder {b8['this_images_per_s']:.0f} / {b1['this_images_per_s']:.0f}" in large
    assert f"previous encoder's {b8['baseline_images_per_s']:.0f} / {b1['baseline_images_per_s']:.0f}" in large
    assert f"{b8['baseline_over_this']:.2f}× / {b1['baseline_over_this']:.2f}×" in large
    assert f"{numpy_large['ms_per_image']:.0f} ms/image ({b8['speedup']:.0f}× / {b1['speedup']:.0f}× slower)" in large
    assert all(r.get("max_level_diff_vs_baseline", 0) == 0 for r in rec["rows"])  # the previous encoder's outputs


def test_the_readmes_classifier_speed_row_is_its_benchmarks_record():
    rec = json.loads((REPO / "docs" / "benchmarks" / "inference_speed_builtin.json").read_text())
    rows = {r["batch"]: r for r in rec["rows"] if r["size"] == "builtin"}
    (line,) = [x for x in README.read_text().splitlines() if x.startswith("| end to end, the built-in classifier")]
    b8, b1 = rows[8], rows[1]
    assert rows[1]["image_hw"] == [96, 96]
    assert "(96², two depth views" in line
    assert f"{b8['images_per_s']:.1f} / {b1['images_per_s']:.1f} images/s" in line
    assert f"{b8['baseline_images_per_s']:.1f} / {b1['baseline_images_per_s']:.1f} images/s" in line
    assert f"({b8['speedup']:.1f}× / {b1['speedup']:.1f}×" in line
    shares = sorted(round(100 * r["share_depth"]) for r in rows.values())
    assert f"depth is still {shares[0]}–{shares[-1]} % of the time" in line
