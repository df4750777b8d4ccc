"""An evaluation's rows gathered into the paper's tables: Markdown, CSV, a plot.

A row is one task's result (``slam.batch.evaluate.row_of``): ``sequence``, ``scenario``,
``group``, ``mode``, ``sweep``, ``status`` (``ok`` | ``error`` | ``timeout`` | ``interrupted`` | ``not a result``),
``message``, the run's ``frames``, ``failed``, ``flagged``, ``fps``, ``seconds`` and, with
ground truth, ``ate_rmse_mm``, ``rpe_trans_mm`` (± ``rpe_trans_std_mm``), ``rpe_rot_deg``
(± ``rpe_rot_std_deg``); SCARED rows also ``map_*``. A *method* is a mode with its swept values:
each method is one row of the summary tables, as the paper's tables have one row per method.

Averages as the paper's: per scenario the mean ± std over the sequences (clips) of that scenario,
the micro average over all of them and the macro average over the scenario means; only rows that
finished (``ok``) with an ATE enter them; the cell counts the runs that did not finish.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Iterable, Optional

import numpy as np

from slam.synth.generate import SCENARIOS as GENERATOR_SCENARIOS

METRIC_KEYS = ("ate_rmse_mm", "rpe_trans_mm", "rpe_trans_std_mm", "rpe_rot_deg", "rpe_rot_std_deg")
MAP_KEYS = ("map_median_mm", "map_mean_mm", "map_coverage", "map_points", "map_note")
CSV_COLUMNS = ("sweep", "sequence", "selection", "scenario", "group", "mode", "status", "message", "resumed",
               "frames", "failed", "flagged", "fps", "seconds", *METRIC_KEYS, *MAP_KEYS, "out")
SCENARIO_ORDER = (*GENERATOR_SCENARIOS, "full")


def method_of(row: dict) -> str:
    """The summary tables' row name of a run: its mode, after its swept values."""
    return f"{row['sweep']} {row['mode']}".strip() if row.get("sweep") else row["mode"]


def methods_of(rows: Iterable[dict]) -> list[str]:
    return list(dict.fromkeys(method_of(r) for r in rows))


def scored(row: dict) -> bool:
    """Whether a row enters the averages: finished, with a finite ATE."""
    v = row.get("ate_rmse_mm")
    return row.get("status") == "ok" and isinstance(v, (int, float)) and math.isfinite(v)


def mean_std(values) -> tuple[Optional[float], Optional[float]]:
    vals = [float(v) for v in values if v is not None]
    if not vals:
        return None, None
    return float(np.mean(vals)), float(np.std(vals))


def fmt(v, digits: int = 3) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{digits}f}"


def fmt_ms(mean, std, digits: int = 3) -> str:
    return "-" if mean is None else f"{mean:.{digits}f} ± {std:.{digits}f}"


def scenarios_of(rows: Iterable[dict]) -> list[str]:
    """The scenarios present, in the generator's order, then the others by name."""
    present = {r.get("scenario") or "" for r in rows} - {""}
    return [s for s in SCENARIO_ORDER if s in present] + sorted(present - set(SCENARIO_ORDER))


# ------------------------------------------------------------------------------------------------
def scenario_summary(rows: list[dict], scenarios: list[str]) -> dict:
    """Per method: ATE mean/std/n per scenario (and how many did not finish), micro (over the runs
    of those scenarios) and macro (over the scenario means)."""
    out = {}
    for method in methods_of(rows):
        mine = [r for r in rows if method_of(r) == method and (r.get("scenario") or "") in scenarios]
        agg: dict = {}
        means = []
        for sc in scenarios:
            of = [r for r in mine if (r.get("scenario") or "") == sc]
            m, s = mean_std(r["ate_rmse_mm"] for r in of if scored(r))
            agg[sc] = {"mean": m, "std": s, "n": sum(scored(r) for r in of), "errors": sum(r["status"] != "ok" for r in of)}
            if m is not None:
                means.append(m)
        m, s = mean_std(r["ate_rmse_mm"] for r in mine if scored(r))
        agg["micro"] = {"mean": m, "std": s, "n": sum(scored(r) for r in mine)}
        m, s = mean_std(means)
        agg["macro"] = {"mean": m, "std": s, "n": len(means)}
        out[method] = agg
    return out


def cell(agg: dict, digits: int = 3) -> str:
    text = fmt_ms(agg["mean"], agg["std"], digits)
    if agg.get("errors"):
        text += f" ({agg['errors']} failed)"
    return text


def scenario_table(rows: list[dict], scenarios: list[str], title: str) -> tuple[str, dict]:
    """The Table-1-style Markdown (ATE mean ± std per scenario, micro and macro averages, a row
    per method) and its figures."""
    summary = scenario_summary(rows, scenarios)
    first = methods_of(rows)[0]
    counts = [sum(method_of(r) == first and (r.get("scenario") or "") == sc for r in rows) for sc in scenarios]
    names = [sc or "(none)" for sc in scenarios]
    lines = [f"### {title}", "",
             "| method | " + " | ".join(names) + " | micro avg. | macro avg. |",
             "|---" * (len(scenarios) + 3) + "|",
             "| # runs | " + " | ".join(map(str, counts)) + " | | |"]
    for method, agg in summary.items():
        lines.append(f"| {method} | " + " | ".join(cell(agg[sc]) for sc in scenarios)
                     + f" | {cell(agg['micro'])} | {cell(agg['macro'])} |")
    return "\n".join(lines), summary


def runs_table(rows: list[dict], with_map: bool = False) -> str:
    """Every run: one line each, errors with their message."""
    map_head = " map median mm | map coverage |" if with_map else ""
    lines = ["### Every run", "",
             "| sequence | selection | scenario | method | status | ATE-RMSE mm | RPE-trans mm | RPE-rot deg | failed | "
             "flagged | fps |" + map_head + " note |",
             "|---" * (12 + (2 if with_map else 0)) + "|"]
    for r in rows:
        sel = r.get("selection") or "all"
        head = f"| {r['sequence']} | {sel} | {r.get('scenario') or '-'} | {method_of(r)} | {r['status']}"
        if r["status"] == "error":
            lines.append(head + " | | | | | | |" + (" | |" if with_map else "") + f" {r.get('message', '')} |")
            continue
        cov = r.get("map_coverage")
        maps = (f" {fmt(r.get('map_median_mm'))} | {'-' if cov is None else f'{100 * cov:.1f} %'} |"
                if with_map else "")
        note = r.get("message") or r.get("map_note") or ("resumed" if r.get("resumed") else "")
        lines.append(head + f" | {fmt(r.get('ate_rmse_mm'))} | {fmt_ms(r.get('rpe_trans_mm'), r.get('rpe_trans_std_mm'))} | "
                     f"{fmt_ms(r.get('rpe_rot_deg'), r.get('rpe_rot_std_deg'), 4)} | {r.get('failed', '-')}/"
                     f"{r.get('frames', '-')} | {r.get('flagged', '-')} | {fmt(r.get('fps'), 1)} |" + maps + f" {note} |")
    return "\n".join(lines)


def write_csv(rows: list[dict], path: Path) -> None:
    """One line per run, the columns of :data:`CSV_COLUMNS` (empty where a run has no value)."""
    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(CSV_COLUMNS)
        for r in rows:
            writer.writerow(["" if r.get(k) is None else r.get(k) for k in CSV_COLUMNS])


def plot(rows: list[dict], scenarios: list[str], path: Path, title: str) -> None:
    """ATE per run, a bar per method (left), and the per-scenario and macro means per method
    (right)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = methods_of(rows)
    runs = list(dict.fromkeys((r["sequence"], r.get("selection") or "") for r in rows))
    fig, axes = plt.subplots(1, 2, figsize=(max(8.0, 0.5 * len(runs) * len(methods) + 6), 4.5),
                             gridspec_kw={"width_ratios": [max(1, len(runs)), max(1, len(scenarios) + 1)]})
    width = 0.8 / max(1, len(methods))
    summary = scenario_summary(rows, scenarios)
    for j, method in enumerate(methods):
        by_run = {(r["sequence"], r.get("selection") or ""): r for r in rows if method_of(r) == method}
        values = [by_run[k]["ate_rmse_mm"] if k in by_run and scored(by_run[k]) else np.nan for k in runs]
        axes[0].bar(np.arange(len(runs)) + (j - (len(methods) - 1) / 2) * width, values, width, label=method)
        agg = summary[method]
        means = [agg[sc]["mean"] if agg[sc]["mean"] is not None else np.nan for sc in scenarios]
        means.append(agg["macro"]["mean"] if agg["macro"]["mean"] is not None else np.nan)
        axes[1].bar(np.arange(len(scenarios) + 1) + (j - (len(methods) - 1) / 2) * width, means, width, label=method)
    axes[0].set_xticks(np.arange(len(runs)))
    axes[0].set_xticklabels([f"{s} {sel}".strip() for s, sel in runs], rotation=45, ha="right", fontsize=8)
    axes[0].set_ylabel("ATE-RMSE (mm)")
    axes[0].set_title("per run")
    axes[1].set_xticks(np.arange(len(scenarios) + 1))
    axes[1].set_xticklabels([*(sc or "(none)" for sc in scenarios), "macro"], rotation=45, ha="right", fontsize=8)
    axes[1].set_title("per scenario")
    axes[1].legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
