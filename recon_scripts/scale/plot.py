"""The scale benchmark's figure: time per stage against N, memory against N and matching pairs/s
per worker."""

from __future__ import annotations

from pathlib import Path


def plot(path: Path, rows: dict, executors: list, per_pair: dict) -> None:
    """Three panels to ``path``: see ``report.report`` for ``rows``, ``executors``, ``per_pair``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    _times(axes[0], rows, per_pair)
    _memory(axes[1], rows)
    _throughput(axes[2], executors)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def _times(ax, rows: dict, per_pair: dict) -> None:
    for mode, style in (("retrieval", "o-"), ("exhaustive", "s--")):
        ns = sorted(n for n, m in rows if m == mode)
        if ns:
            for key, colour in (("extract", "C0"), ("match", "C1"), ("total", "k")):
                ax.plot(
                    ns,
                    [rows[(n, mode)][key] / 60 for n in ns],
                    style,
                    color=colour,
                    label=f"{mode}: {key}",
                )
            ax.plot(
                ns,
                [rows[(n, mode)]["cpu"] / 60 for n in ns],
                style,
                color="C2",
                label=f"{mode}: CPU (all stages)",
            )
    if per_pair:
        n0 = min(per_pair)
        ns = [n0, 200, 1000]
        ax.plot(
            ns,
            [n * (n - 1) / 2 * per_pair[n0][0] / 60 for n in ns],
            ":",
            color="C3",
            label="exhaustive match, projected",
        )
    ax.axhline(60, color="grey", lw=0.8)
    ax.set(
        xscale="log",
        yscale="log",
        xlabel="photos N",
        ylabel="minutes",
        title="time per stage (wall, shared machine)",
    )
    ax.legend(fontsize=7)


def _memory(ax, rows: dict) -> None:
    ns = sorted(n for n, m in rows if m == "retrieval")
    retrieval = [rows[(n, "retrieval")] for n in ns]
    ax.plot(ns, [r["rss_match"] for r in retrieval], "o-", label="match stage peak RSS (MB)")
    ax.plot(ns, [r["rss_run"] for r in retrieval], "s-", label="run peak RSS (MB, max over stages)")
    ax2 = ax.twinx()
    ax2.plot(
        ns,
        [r["held"] or 0 for r in retrieval],
        "^:",
        color="C3",
        label="images held at once (max)",
    )
    ax2.set_ylabel("images held")
    ax.set(
        xscale="log",
        xlabel="photos N",
        ylabel="MB",
        title="memory (retrieval)",
        ylim=(0, 1.3 * max([r["rss_run"] for r in rows.values()] or [1])),
    )
    ax2.set_ylim(0, 140)
    ax.legend(fontsize=7, loc="upper left")
    ax2.legend(fontsize=7, loc="lower right")


def _throughput(ax, executors: list) -> None:
    for kind, marker in (("local", "o"), ("ray_private", "s"), ("ray_2nodes", "^")):
        pts = [(r["workers"], r["pairs_per_s"]) for r in executors if r["config"].startswith(kind)]
        if pts:
            ax.plot(*zip(*pts), marker, label=kind, ms=8)
    ones = [r["pairs_per_s"] for r in executors if r["workers"] == 1]
    if ones:
        ax.plot(
            [1, 2],
            [min(ones), 2 * min(ones)],
            ":",
            color="grey",
            label="linear from the slower 1-worker run",
        )
    ax.set(xlabel="workers", ylabel="pairs / s", title="matching throughput", xticks=[1, 2])
    ax.legend(fontsize=7)
