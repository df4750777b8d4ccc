"""Each protocol's report: the paper's tables for its rows (Markdown) and their figures (JSON).

* ``folder``: ATE per scenario with micro and macro averages (the shape of the paper's Table 1).
* ``stereomis``: Table 1 (the 150-frame clips per surgical scenario) and Table 2 (the full
  test sequences: ATE, RPE-trans and RPE-rot per sequence, their average, the mean per subject
  and the macro average over subjects).
* ``scared``: Table 3 (ATE per keyframe sequence; ``avg.`` over the paper's four keyframes that
  were evaluated, ``SCARED avg.`` over every evaluated keyframe) and per method the details with
  the map's accuracy.

Every report ends with the list of every run (``slam.batch.tables.runs_table``).
"""
from __future__ import annotations

from slam.batch.protocols import CLIP_SCENARIOS, PAPER_KEYFRAMES
from slam.batch.tables import (fmt, fmt_ms, mean_std, method_of, methods_of, runs_table, scenario_table,
                               scenarios_of, scored)

TABLE2_KEYS = ("ate_rmse_mm", "rpe_trans_mm", "rpe_rot_deg")


def folder_report(rows: list[dict]) -> tuple[list[str], dict]:
    scenarios = scenarios_of(rows) or [""]
    md, summary = scenario_table(rows, scenarios, "ATE-RMSE (mean ± std, mm) per scenario")
    return [md, runs_table(rows)], {"scenarios": summary}


# ------------------------------------------------------------------------------------------------
def stereomis_table2(rows: list[dict]) -> tuple[str, dict]:
    """Table 2 style: per method the full sequences, their average, subject means, macro average."""
    lines = ["### Table 2 style: full test sequences", ""]
    out = {}
    for method in methods_of(rows):
        mine = [r for r in rows if method_of(r) == method]
        ok = [r for r in mine if scored(r)]
        avg = {k: dict(zip(("mean", "std"), mean_std(r[k] for r in ok))) for k in TABLE2_KEYS}
        avg["n"] = len(ok)
        subjects = {}
        for subject in sorted({r["group"] for r in ok}):
            of = [r for r in ok if r["group"] == subject]
            subjects[subject] = {k: mean_std(r[k] for r in of)[0] for k in TABLE2_KEYS}
            subjects[subject]["n"] = len(of)
        macro = {k: dict(zip(("mean", "std"), mean_std(v[k] for v in subjects.values()))) for k in TABLE2_KEYS}
        macro["n"] = len(subjects)
        out[method] = {"average": avg, "subjects": subjects, "macro": macro,
                       "errors": sum(r["status"] != "ok" for r in mine)}
        lines += [f"**{method}**", "",
                  "| sequence | frames | failed frames | ATE-RMSE mm | RPE-trans mm | RPE-rot deg |",
                  "|---|---|---|---|---|---|"]
        for r in mine:
            if not scored(r):
                lines.append(f"| {r['sequence']} | {r['status']}: {r.get('message', '')} | | | | |")
                continue
            lines.append(f"| {r['sequence']} | {r.get('frames', 0)} | {r.get('failed', 0)} | {fmt(r['ate_rmse_mm'], 2)} | "
                         f"{fmt_ms(r.get('rpe_trans_mm'), r.get('rpe_trans_std_mm'), 2)} | "
                         f"{fmt_ms(r.get('rpe_rot_deg'), r.get('rpe_rot_std_deg'), 3)} |")

        def ms(agg, key, digits=2):
            return fmt_ms(agg[key]["mean"], agg[key]["std"], digits)

        lines.append(f"| **average ({avg['n']} sequences)** | | | {ms(avg, 'ate_rmse_mm')} | {ms(avg, 'rpe_trans_mm')} | "
                     f"{ms(avg, 'rpe_rot_deg', 3)} |")
        for subject, v in subjects.items():
            lines.append(f"| {subject} (subject mean, {v['n']}) | | | {fmt(v['ate_rmse_mm'], 2)} | {fmt(v['rpe_trans_mm'], 2)} | "
                         f"{fmt(v['rpe_rot_deg'], 3)} |")
        lines.append(f"| **macro avg. ({macro['n']} subjects)** | | | {ms(macro, 'ate_rmse_mm')} | "
                     f"{ms(macro, 'rpe_trans_mm')} | {ms(macro, 'rpe_rot_deg', 3)} |")
        lines.append("")
    return "\n".join(lines).rstrip(), out


def stereomis_report(rows: list[dict]) -> tuple[list[str], dict]:
    sections, figures = [], {}
    clips = [r for r in rows if r["scenario"] in CLIP_SCENARIOS]
    if clips:
        md, figures["table1"] = scenario_table(clips, list(CLIP_SCENARIOS),
                                               "Table 1 style: ATE-RMSE (mean ± std, mm) per surgical scenario")
        sections.append(md)
    full = [r for r in rows if r["scenario"] == "full"]
    if full:
        md, figures["table2"] = stereomis_table2(full)
        sections.append(md)
    sections.append(runs_table(rows))
    return sections, figures


# ------------------------------------------------------------------------------------------------
def scared_report(rows: list[dict]) -> tuple[list[str], dict]:
    names = list(dict.fromkeys(r["sequence"] for r in rows))
    by = {(r["sequence"], method_of(r)): r for r in rows}
    table3 = ["### Table 3 style: ATE-RMSE (mm) per SCARED keyframe sequence", "",
              "| method | " + " | ".join(names) + " | avg. | SCARED avg. |",
              "|---" * (len(names) + 3) + "|"]
    figures = {}
    details = []
    with_map = any(r.get("map_median_mm") is not None or r.get("map_note") for r in rows)
    for method in methods_of(rows):
        ok = [r for r in rows if method_of(r) == method and scored(r)]
        cells = []
        for n in names:
            r = by.get((n, method))
            cells.append("-" if r is None else (fmt(r["ate_rmse_mm"], 2) if scored(r) else r["status"]))
        paper = [r["ate_rmse_mm"] for r in ok if r["sequence"] in PAPER_KEYFRAMES]
        paper_mean = mean_std(paper)[0]
        agg = {"n": len(ok), "errors": sum(method_of(r) == method and r["status"] != "ok" for r in rows),
               "paper_avg_ate_mm": {"mean": paper_mean, "n": len(paper)}}
        for key in ("ate_rmse_mm", "rpe_trans_mm", "rpe_rot_deg", "map_median_mm", "map_mean_mm", "map_coverage"):
            agg[key] = dict(zip(("mean", "std"), mean_std(r.get(key) for r in ok)))
        figures[method] = agg
        avg = "-" if paper_mean is None else f"{paper_mean:.2f}" + (
            "" if len(paper) == len(PAPER_KEYFRAMES) else f" ({len(paper)}/{len(PAPER_KEYFRAMES)})")
        table3.append(f"| {method} | " + " | ".join(cells) + f" | {avg} | "
                      f"{fmt_ms(agg['ate_rmse_mm']['mean'], agg['ate_rmse_mm']['std'], 2)} |")
        if with_map:
            cov = agg["map_coverage"]["mean"]
            details.append(f"| {method} | {agg['n']} | {fmt_ms(agg['map_median_mm']['mean'], agg['map_median_mm']['std'])} | "
                           f"{fmt_ms(agg['map_mean_mm']['mean'], agg['map_mean_mm']['std'])} | "
                           f"{'-' if cov is None else f'{100 * cov:.1f} %'} |")
    table3 += ["", f"avg. = mean over the paper's keyframes {', '.join(PAPER_KEYFRAMES)} that were evaluated; "
                   "SCARED avg. = mean ± std over every evaluated keyframe."]
    sections = ["\n".join(table3)]
    if with_map:
        sections.append("\n".join(["### Map accuracy against the keyframes' depth (mean ± std over keyframes)", "",
                                   "| method | keyframes | median abs. error mm | mean abs. error mm | coverage |",
                                   "|---|---|---|---|---|", *details]))
    sections.append(runs_table(rows, with_map=with_map))
    return sections, {"table3": figures}


REPORTS = {"folder": folder_report, "stereomis": stereomis_report, "scared": scared_report}
