"""Training curves: ``python -m maipp_bench.curves RUN_OR_CARD... --out curves.png``.

Reads a run folder's ``curve.jsonl`` or a shipped checkpoint's JSON card and plots, against
env frames (``--x updates`` or ``--x minutes`` of update time instead: runs of different
batch widths or machines compare per update or per minute), the final Tr(P) of the training
episodes, the held-out evaluation's Tr(P)
(greedy decoding unless the run's ``eval_method`` says otherwise) and the mean reward per
decision. A card's selected update (the weights it exports) is marked by a dashed line.
A fine-tune's card (one with ``init``) is drawn from the frames (updates, minutes) its
starting network had already been trained on, so it continues that network's curve.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.ticker import FuncFormatter  # noqa: E402


def init_frames(card: dict[str, Any]) -> int:
    """Env frames of the training behind a fine-tune's starting network (0 without one)."""
    return card.get("frames_with_init", card.get("frames", 0)) - card.get("frames", 0)


def read_curve(source: str | Path) -> list[dict[str, Any]]:
    """The curve rows of a run folder (``curve.jsonl``) or a checkpoint card (``.json``);
    a fine-tune card's ``frames`` count its starting network's training too."""
    path = Path(source)
    if path.is_dir():
        path = path / "curve.jsonl"
    if path.suffix == ".jsonl":
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    card = json.loads(path.read_text())
    offset = init_frames(card)
    return [r | {"frames": r["frames"] + offset} for r in card["curve"]]


# --x choices: (curve field, axis label, divisor).
X_AXES = {"frames": ("frames", "env frames", 1),
          "updates": ("update", "updates", 1),
          "minutes": ("wall_s", "minutes of update time", 60)}


def init_offsets(source: str | Path) -> dict[str, float]:
    """Where a fine-tune card's curve starts on the ``update`` and ``wall_s`` axes: the
    updates and seconds of every network before it (a fine-tune of a fine-tune counts
    both; frames are offset by :func:`read_curve`); empty for a run folder or a card
    trained from scratch."""
    path = Path(source)
    if path.is_dir() or path.suffix != ".json":
        return {}
    card = json.loads(path.read_text())
    chain, node = [], card.get("init") or {}
    while node:
        chain.append(node)
        node = node.get("init") or {}
    if not chain:
        return {}
    wall = (card["wall_s_with_init"] - card.get("wall_s", 0) if "wall_s_with_init" in card
            else sum(n.get("wall_s", 0) for n in chain))
    return {"update": sum(n.get("update", 0) for n in chain), "wall_s": wall}


def x_value(row: dict[str, Any], axis: str, offsets: dict[str, float] | None = None) -> float:
    """A curve row's position on the ``axis`` of :data:`X_AXES`."""
    key, _, divisor = X_AXES[axis]
    return (row[key] + (offsets or {}).get(key, 0)) / divisor


def selected_frames(source: str | Path) -> int | None:
    """Env frames at the update a checkpoint card selected, counted as ``read_curve``
    counts them (None for a run folder)."""
    path = Path(source)
    if path.is_dir() or path.suffix != ".json":
        return None
    card = json.loads(path.read_text())
    offset = init_frames(card)
    at = [r["frames"] + offset for r in card["curve"] if r["update"] == card.get("selected_update")]
    return at[0] if at else None


def eval_title(sources: dict[str, list[dict[str, Any]]]) -> str:
    """Title of the held-out panel: the evaluations it shows, by tag (``greedy@3``)."""
    # Rows written before eval tags existed were greedy decoding (at one of the tagged
    # greedy budgets, if any appear).
    tags = {r.get("eval/tag", "greedy") for rows in sources.values() for r in rows
            if "eval/trace" in r}
    if any(t.startswith("greedy@") for t in tags):
        tags.discard("greedy")
    return "Tr(P_f), held-out " + (" / ".join(sorted(tags)) or "greedy") + " eval"


def figure(sources: dict[str, list[dict[str, Any]]],
           selected: dict[str, float] | None = None, x: str = "frames",
           offsets: dict[str, dict[str, float]] | None = None,
           xmax: float | None = None) -> plt.Figure:
    """Up to three panels against the ``x`` axis of :data:`X_AXES` (one no curve has a
    point for is left out), one line per named curve in the same colour in every panel (a
    curve may have no points in one, e.g. a run without held-out evaluations), a dashed
    line at each curve's ``selected`` position on that axis; ``offsets`` shift a
    fine-tune's curve (:func:`init_offsets`); ``xmax`` shows the axis from 0 to there
    (short runs beside a long one)."""
    if x not in X_AXES:
        raise ValueError(f"x={x!r}; valid: {', '.join(X_AXES)}")
    titles = {"trace_final": "Tr(P_f), training episodes", "eval/trace": eval_title(sources),
              "reward_per_decision": "reward per decision"}
    # each panel's finite points per curve; a panel no curve has a point for (no run
    # evaluated on held-out episodes) is left out
    points = {key: {name: [(x_value(r, x, (offsets or {}).get(name)), r[key]) for r in rows
                           if key in r and r[key] == r[key]]
                    for name, rows in sources.items()} for key in titles}
    panels = [key for key, curves in points.items() if any(curves.values())]
    if not panels:
        raise ValueError("no curve has any point to draw")
    fig, axes = plt.subplots(1, len(panels), figsize=(13 * len(panels) / 3, 3.6),
                             constrained_layout=True, squeeze=False)
    axes = axes[0]
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    if len(sources) > len(cycle):  # past the cycle's ten, colours would repeat: tab20's
        cycle = [plt.get_cmap("tab20")(i) for i in range(20)]
    colors = {name: cycle[i % len(cycle)] for i, name in enumerate(sources)}
    for ax, key in zip(axes, panels):
        for name, pts in points[key].items():
            if pts:
                ax.plot(*zip(*pts), marker="." if len(pts) < 40 else None, label=name,
                        color=colors[name])
            if selected and name in selected:
                ax.axvline(selected[name], color=colors[name], ls="--", lw=1,
                           label=f"{name}: selected update")
        ax.set_title(titles[key])
        ax.set_xlabel(X_AXES[x][1])
        if xmax is not None:  # every axis here starts at 0: a fine-tune's too (offsets)
            ax.set_xlim(0, xmax)
        if x == "frames":  # thousands as "20k": full numbers run into each other
            ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v / 1000:g}k" if v else "0"))
        ax.grid(alpha=0.3)
    # One legend beside the panels (not over them): every curve once, even one that has
    # no points in the first panel.
    entries = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            entries.setdefault(label, handle)
    fig.legend(entries.values(), entries.keys(), loc="outside right upper", fontsize=8)
    return fig


def plot_curves(sources: dict[str, list[dict[str, Any]]], out: str | Path,
                selected: dict[str, float] | None = None, x: str = "frames",
                offsets: dict[str, dict[str, float]] | None = None,
                xmax: float | None = None) -> Path:
    """:func:`figure`, written to ``out`` (PNG)."""
    fig = figure(sources, selected, x, offsets, xmax)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m maipp_bench.curves", description=__doc__)
    p.add_argument("sources", nargs="+", help="run folders or checkpoint cards (NAME=PATH "
                   "to name a line)")
    p.add_argument("--out", required=True)
    p.add_argument("--x", choices=list(X_AXES), default="frames",
                   help="the horizontal axis (minutes: of update time, from the curve's wall_s)")
    p.add_argument("--xmax", type=float, help="cut the horizontal axis at this value")
    args = p.parse_args(argv)
    if args.xmax is not None and args.xmax <= 0:
        p.error(f"--xmax must be positive, got {args.xmax}")
    curves, selected, offsets = {}, {}, {}
    for src in args.sources:
        name, sep, path = src.partition("=")
        name, path = (name, path) if sep else (Path(src).stem, src)
        curves[name] = read_curve(path)
        offsets[name] = init_offsets(path)
        if (frames := selected_frames(path)) is not None:
            at = [r for r in curves[name] if r["frames"] == frames]
            selected[name] = x_value(at[0], args.x, offsets[name])
    print(f"wrote {plot_curves(curves, args.out, selected, args.x, offsets, args.xmax)}")


if __name__ == "__main__":
    main()
