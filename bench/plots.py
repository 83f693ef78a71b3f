"""The experiments' figures (matplotlib, Agg backend: no display needed)."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import matplotlib.ticker
import numpy as np

from bench.experiments.baselines import FLOW_EDGES, Outcome
from bench.experiments.streaming import PAPER_PEAK_BPS, StreamingPoint

matplotlib.use("Agg")  # files only; pyplot picks the backend lazily, at the first figure

TRACKING_GAP_S = 0.05
"""A longer pause between two poses is a tracking loss."""


def streaming(points: list[StreamingPoint], path: Path) -> None:
    """Box plots of BER and goodput per N, a row per ambient lux level and a colour per
    (profile, refresh rate), the same in every row."""
    labels = sorted({(p.profile, p.refresh_hz) for p in points})
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    colour = {label: colours[i % len(colours)] for i, label in enumerate(labels)}
    cells = sorted({p.cells for p in points})
    levels = sorted({p.lux for p in points})
    fig, axes = plt.subplots(len(levels), 2, figsize=(11, 4.2 * len(levels)), squeeze=False)
    for lux, (ax_ber, ax_rate) in zip(levels, axes, strict=True):
        groups: dict[tuple[str, float], dict[int, list[StreamingPoint]]] = defaultdict(
            lambda: defaultdict(list)
        )
        for p in points:
            if p.lux == lux:
                groups[(p.profile, p.refresh_hz)][p.cells].append(p)
        width = 0.8 / len(groups)
        for g, (label, by_n) in enumerate(sorted(groups.items())):
            present = [n for n in cells if n in by_n]
            pos = [cells.index(n) + (g - (len(groups) - 1) / 2) * width for n in present]
            style = {
                "widths": width * 0.9,
                "patch_artist": True,
                "boxprops": {"facecolor": colour[label], "alpha": 0.6},
                "medianprops": {"color": "black"},
            }
            # Runs that never read a frame have no BER: they show in the goodput panel as zeros.
            ber = {n: [100 * p.ber for p in by_n[n] if p.ber is not None] for n in present}
            read = [n for n in present if ber[n]]
            if read:
                ax_ber.boxplot(
                    [ber[n] for n in read], positions=[pos[present.index(n)] for n in read], **style
                )
            ax_rate.boxplot(
                [[p.goodput_bps / 1e3 for p in by_n[n]] for n in present], positions=pos, **style
            )
            name = f"{label[0]} {label[1]:g} Hz"
            ax_rate.plot([], [], "s", color=colour[label], alpha=0.6, label=name)
            limit = [by_n[n][0].raw_bps / 1e3 for n in present]
            ax_rate.plot(pos, limit, "_", color=colour[label], markersize=14, markeredgewidth=2)
        ax_rate.axhline(
            PAPER_PEAK_BPS / 1e3, color="grey", ls="--", lw=1, label="paper peak, 114 kbit/s"
        )
        ax_rate.plot(
            [], [], "_", color="black", markersize=14, label="physical limit N² x frame rate"
        )
        for ax, title in ((ax_ber, "BER before FEC [%]"), (ax_rate, "goodput after FEC [kbit/s]")):
            ax.set_xticks(range(len(cells)), [f"{n}x{n}" for n in cells])
            ax.set_xlim(-0.5, len(cells) - 0.5)
            ax.set_xlabel("payload cells")
            ax.set_title(f"{title}, {lux:g} lux")
            ax.grid(alpha=0.3)
        ax_rate.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def trajectory(
    t_us: np.ndarray, estimate: np.ndarray, truth: np.ndarray, title: str, path: Path
) -> None:
    """Estimated (aligned, (n, 3)) vs ground-truth (n, 3) camera positions over time, like the
    paper's figure."""
    fig, axes = plt.subplots(3, 1, figsize=(8, 6), sharex=True)
    t = (t_us - t_us[0]) / 1e6
    # Break the lines where tracking was lost rather than join the poses on either side.
    gap = np.flatnonzero(np.diff(t) > TRACKING_GAP_S) + 1
    t = np.insert(t, gap, np.nan)
    estimate, truth = (
        np.insert(estimate, gap, np.nan, axis=0),
        np.insert(truth, gap, np.nan, axis=0),
    )
    for i, (ax, axis) in enumerate(zip(axes, "xyz", strict=True)):
        ax.plot(t, truth[:, i] * 100, color="black", lw=1.2, label="ground truth")
        ax.plot(
            t,
            estimate[:, i] * 100,
            color="tab:red",
            lw=0.8,
            ls="--",
            label="estimate (Umeyama-aligned)",
        )
        ax.set_ylabel(f"{axis} [cm]")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8, loc="upper right")
    axes[0].set_title(title)
    axes[-1].set_xlabel("time since the first pose [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def comparison(outcomes: list[Outcome], path: Path) -> None:
    """Left: success rate per optical-flow bin; right: throughput per system."""
    edges = np.array(FLOW_EDGES)
    centres = (edges[:-1] + edges[1:]) / 2
    by_system: dict[str, list[Outcome]] = defaultdict(list)
    for o in outcomes:
        by_system[o.system].append(o)
    fig, (ax_ok, ax_rate) = plt.subplots(1, 2, figsize=(11, 4.2))
    names = sorted(by_system, key=lambda s: (not s.startswith("ours"), s))
    rates = []
    for name in names:
        flow = np.concatenate([o.flow for o in by_system[name]])
        got = np.concatenate([o.received for o in by_system[name]])
        bins = np.digitize(flow, edges) - 1
        share = [
            got[bins == b].mean() * 100 if np.any(bins == b) else np.nan
            for b in range(len(centres))
        ]
        ax_ok.plot(
            centres,
            share,
            "o--" if name.endswith("blank") else "o-",
            label=name,
            lw=2.5 if name.startswith("ours") else 1.2,
        )
        rates.append(np.mean([o.throughput_bps for o in by_system[name]]))
    ax_ok.set_xlabel("marker optical flow [paper px/ms], bin centres")
    ax_ok.set_ylabel("codes / data frames received [%]")
    ax_ok.set_ylim(-5, 105)
    ax_ok.grid(alpha=0.3)
    ax_ok.legend(fontsize=7)
    ax_rate.barh(range(len(names)), rates, color="tab:blue")
    for i, rate in enumerate(rates):
        ax_rate.annotate(
            f"{rate:.0f}",
            (max(rate, 1.0), i),
            xytext=(3, 0),
            textcoords="offset points",
            va="center",
            fontsize=8,
        )
    ax_rate.set_yticks(range(len(names)), names, fontsize=8)
    ax_rate.set_xscale("log")
    ax_rate.set_xlim(left=1.0)
    ax_rate.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    ax_rate.set_xlabel("throughput [bit/s], log scale")
    ax_rate.grid(alpha=0.3, axis="x")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
