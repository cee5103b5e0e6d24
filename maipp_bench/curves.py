"""Training curves: ``python -m maipp_bench.curves RUN_OR_CARD... --out curves.png``.

Reads a run folder's ``curve.jsonl`` or a shipped checkpoint's JSON card and plots, against
env frames, the final Tr(P) of the training episodes, the held-out evaluation's Tr(P)
(greedy decoding unless the run's ``eval_method`` says otherwise) and the mean reward per
decision. A card's selected update (the weights it exports) is marked by a dashed line.
A fine-tune's card (one with ``init``) is drawn from the frames its starting network had
already been trained on, so it continues that network's curve.
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
           selected: dict[str, int] | None = None) -> plt.Figure:
    """Three panels, one line per named curve in the same colour in every panel (a curve
    may have no points in one, e.g. a run without held-out evaluations), a dashed line at
    each curve's ``selected`` frames."""
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6), constrained_layout=True)
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    if len(sources) > len(cycle):  # past the cycle's ten, colours would repeat: tab20's
        cycle = [plt.get_cmap("tab20")(i) for i in range(20)]
    colors = {name: cycle[i % len(cycle)] for i, name in enumerate(sources)}
    panels = [("trace_final", "Tr(P_f), training episodes"),
              ("eval/trace", eval_title(sources)),
              ("reward_per_decision", "reward per decision")]
    for ax, (key, title) in zip(axes, panels):
        for name, rows in sources.items():
            pts = [(r["frames"], r[key]) for r in rows if key in r and r[key] == r[key]]
            if pts:
                ax.plot(*zip(*pts), marker="." if len(pts) < 40 else None, label=name,
                        color=colors[name])
            if selected and name in selected:
                ax.axvline(selected[name], color=colors[name], ls="--", lw=1,
                           label=f"{name}: selected update")
        ax.set_title(title)
        ax.set_xlabel("env frames")
        # Thousands as "20k": full numbers run into each other on narrow panels.
        ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x / 1000:g}k" if x else "0"))
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
                selected: dict[str, int] | None = None) -> Path:
    """:func:`figure`, written to ``out`` (PNG)."""
    fig = figure(sources, selected)
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
    args = p.parse_args(argv)
    curves, selected = {}, {}
    for src in args.sources:
        name, sep, path = src.partition("=")
        name, path = (name, path) if sep else (Path(src).stem, src)
        curves[name] = read_curve(path)
        if (frames := selected_frames(path)) is not None:
            selected[name] = frames
    print(f"wrote {plot_curves(curves, args.out, selected)}")


if __name__ == "__main__":
    main()
