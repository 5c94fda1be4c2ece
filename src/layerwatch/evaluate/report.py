"""The evaluation report: Markdown, matplotlib charts (Agg, OO API) and a rich table.

Charts (paper Figs. 13-14 and further):

* ``a_percent.png``   mean a% on failed vs clean layers per measure (each at its best T_S);
* ``discriminative_power.png``  DP (percentage points) per measure and failure type;
* ``auroc.png``       AUROC heatmap, measures x failure types;
* ``roc.png``         ROC curves of the recommended setting per failure type;
* ``threshold_scan.png``  worst-type AUROC of every measure against T_S.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from rich.table import Table

from layerwatch.evaluate.stats import false_alarm_rate, roc_curve
from layerwatch.evaluate.summary import Summary

__all__ = ["write_report", "rich_table"]

TARGETS = {"auroc": 0.95, "iou": 0.5, "false_alarms_per_1000": 1.0, "clean_block_share": 0.95}


def _fig(w=7.0, h=4.0):
    fig = Figure(figsize=(w, h), dpi=110)
    FigureCanvasAgg(fig)
    return fig


def _charts(s: Summary, out: Path) -> list[str]:
    names = list(s.metrics)
    x = np.arange(len(names))
    files = []
    # a% failed vs clean
    fig = _fig(8, 4)
    ax = fig.add_subplot()
    width = 0.8 / (len(s.types) + 1)
    ax.bar(x - 0.4 + width / 2, 100 * s.a_clean, width, label="clean", color="0.6")
    for k, t in enumerate(s.types):
        ax.bar(x - 0.4 + width * (k + 1.5), 100 * s.a_failed[:, k], width, label=t)
    ax.set_xticks(x, names, rotation=45, ha="right")
    ax.set_ylabel("mean a% (each measure at its best T_S)")
    ax.legend(fontsize=7, ncol=4)
    fig.tight_layout()
    fig.savefig(out / "a_percent.png")
    files.append("a_percent.png")
    # discriminative power
    fig = _fig(8, 4)
    ax = fig.add_subplot()
    for k, t in enumerate(s.types):
        ax.plot(x, s.dp[:, k], "o-", label=t)
    ax.set_xticks(x, names, rotation=45, ha="right")
    ax.set_ylabel("DP = mean a% failed - mean a% clean (pp)")
    ax.axhline(0, color="k", lw=0.5)
    ax.legend(fontsize=7, ncol=3)
    fig.tight_layout()
    fig.savefig(out / "discriminative_power.png")
    files.append("discriminative_power.png")
    # AUROC heatmap
    fig = _fig(7, 5)
    ax = fig.add_subplot()
    auc = np.array([s.auc[m, :, s.best_t[m]] for m in range(len(names))])
    im = ax.imshow(auc, vmin=0.5, vmax=1.0, cmap="RdYlGn", aspect="auto")
    ax.set_yticks(x, [f"{n} (T={s.thresholds[s.best_t[m]]:.2f})" for m, n in enumerate(names)])
    ax.set_xticks(np.arange(len(s.types)), s.types, rotation=30, ha="right")
    for m in range(len(names)):
        for k in range(len(s.types)):
            ax.text(k, m, f"{auc[m, k]:.2f}", ha="center", va="center", fontsize=7)
    fig.colorbar(im, ax=ax, label="AUROC")
    fig.tight_layout()
    fig.savefig(out / "auroc.png")
    files.append("auroc.png")
    # ROC curves of the recommended setting
    fig = _fig(5, 5)
    ax = fig.add_subplot()
    for t in s.types:
        fpr, tpr, _ = roc_curve(s.scores[t], s.scores["clean"])
        ax.plot(fpr, tpr, label=t)
    ax.plot([0, 1], [0, 1], "k:", lw=0.5)
    ax.set_xlabel("false positive rate (clean layers)")
    ax.set_ylabel("true positive rate")
    ax.set_title(f"{names[s.rec_metric]}, T_S = {s.thresholds[s.rec_t]:.2f}", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "roc.png")
    files.append("roc.png")
    # threshold scan
    fig = _fig(7, 4)
    ax = fig.add_subplot()
    for m, n in enumerate(names):
        ax.plot(s.thresholds, np.nanmin(s.auc[m], axis=0), label=n)
    ax.set_xlabel("block threshold T_S")
    ax.set_ylabel("worst-type AUROC")
    ax.legend(fontsize=6, ncol=3)
    fig.tight_layout()
    fig.savefig(out / "threshold_scan.png")
    files.append("threshold_scan.png")
    return files


def _fmt(v, pct=False, nd=2):
    if v is None or not np.isfinite(v):
        return "n/a"
    return f"{100 * v:.1f}" if pct else f"{v:.{nd}f}"


def _rate_row(target: str, count: int, n: int, detail: str, bound_digits: int = 1) -> str:
    """A targets-table row for ``count`` events in ``n`` clean layers against <= 1 per 1000 (with its 95 % bound)."""
    rate, up = false_alarm_rate(count, n)
    return f"| {target} | <= 1 | {rate:.1f} ({detail}; 95 % upper bound {up:.{bound_digits}f}) | {_rate_met(count, n)} |"


def _rate_met(count: int, n: int) -> str:
    """Whether ``count`` events in ``n`` clean layers meet <= 1 per 1000, one rule for every row.

    ``"yes"`` when the one-sided 95 % bound is <= 1 (shown); ``"at the rate (not at 95 %)"`` when the
    observed rate is <= 1 but the sample cannot bound it (3 in 3014: 0.995, bound 2.6); ``"consistent"``
    for no event in too small a sample; else ``"no"``.
    """
    rate, up = false_alarm_rate(count, n)
    if up <= 1:
        return "yes"
    if count == 0:
        return "consistent"
    return "at the rate (not at 95 %)" if rate <= 1 else "no"


#: the report's fixed sections: definitions of the figures and what limits them
_DEFINITIONS_AND_LIMITS = ["", "## Definitions", "",
      "- **a%** (eq. 5): anomalous block area over the printed area of the layer, blocks below T_S counted "
      "(considered blocks: footprint plus `footprint_margin_mm`, seen by the camera).",
      "- **AUROC**: Mann-Whitney U / (P N) of a% between layers with the failure present and clean layers "
      "(clean prints and the layer before each onset); own rank implementation, tested against brute-force "
      "pair counting.",
      "- **Discriminative power (DP)**, our reading of the paper's Fig. 14: mean a% on failed layers minus "
      "mean a% on clean layers, percentage points (higher = better separated).",
      "- **IoU**: pixels of the anomalous blocks' tiles vs the simulator's failed region (`truth_area`), "
      "on failed layers with a failure of size >= 5 mm, averaged per type. The truth is what the camera sees "
      "of the failure (`simulate/truth.py`: each top-view pixel's ray marched through the simulated scene and "
      "through the scene with the failure undone): the holes of a patch still open (closed by 3 mm into a "
      "region), the object or strands where the part does not hide them, for a layer shift where the view "
      "differs by more than half a layer in height (the overhang, the place left, the shifted walls facing the "
      "camera; not where the shifted top covers the planned one), for a detachment all of the moved part as "
      "seen and the place it left. A thin-wall defect on a part without thin walls cuts the outer perimeter: "
      "a *wall gap*. In the modes section a region typed as a layer shift marks where the layers since the "
      "shift was first seen, projected through the camera centre and carried by the registered move, differ "
      "in height from the plan; one typed as a detachment the whole part as the camera sees it, where the "
      "plan has it and carried; both also in place of the tiles grown from their blocks. "
      "A region typed as a foreign body marks its pixels unlike both the bed and the part instead, where "
      "they cover at least half of the region's own area.",
      "- **False alarms**: clean layers whose a% exceeds the pause ratio, per 1000 clean layers "
      "(Clopper-Pearson one-sided 95 % bound given too).", "",
      "## What limits the figures", "",
      "- **a% dilutes local defects.** An infill patch of 5-12 mm or a thin-wall gap covers a few % of a "
      "large layer, about as much as the clean-layer noise; its blocks are found (see the overlays) but the "
      "layer score barely moves. The largest-region AUROC table above measures a score without that dilution.",
      "- **Clean layers are not clean in HOG space.** Only the reported share of printed-area blocks of clean "
      "layers reaches cosine > 0.7 (target 95 %): the camera sees the part at 45 deg, so walls below the top "
      "layer and lower surfaces seen through holes are misregistered in the top view of the top layer's plane "
      "(parallax), the simulated bead noise/lighting differs from the reference renderer by design, and bead-scale "
      "texture is at the resolution limit of a 1280x720 camera. The operating points therefore use low T_S "
      "(only strongly dissimilar blocks count), which costs localisation (IoU) because a failed region's "
      "weaker blocks are not counted.",
      "- **False alarms**: the pause ratio is set above every clean layer of the scored sample, whose ~300 clean "
      "layers can only bound the rate at ~9 per 1000 (95 %); `--clean-layers N` adds whole clean prints and "
      "counts single layers above the ratio, the policy's notices and its pauses separately. Showing <= 1 per "
      "1000 at 95 % needs about 3000 clean layers with no event of that kind.",
      "- **Layer shifts** are drawn 1.5-5 mm, so few reach the 5 mm IoU class (n/a = none in the sample).",
      "- The simulator is ours, so these are figures on simulated photos only; no labelled real photos exist.",
      ""]


def type_label(t: str, setup: dict) -> str:
    """A failure type's row label: a thin-wall defect on a part without thin walls is a wall gap (``setup["thin_walls"]``)."""
    if t == "thin_wall" and setup.get("thin_walls") is False:
        return "thin_wall (wall gap: no thin wall in this part)"
    return t


def _header(s: Summary, setup: dict, seconds: float) -> list[str]:
    """Title, set-up line, layer counts and the recommendation."""
    r, j = s.rec_metric, s.rec_t
    names = s.metrics
    L = ["# Evaluation of the twelve HOG similarity measures on simulated prints", ""]
    L += [f"Generated by `layerwatch evaluate` in {seconds:.0f} s ({setup.get('n_frames')} simulated layer photos, "
          f"{setup.get('n_scenarios')} simulated prints, part `{Path(str(setup.get('toolpath'))).name}` "
          f"({setup.get('toolpath_layers')} layers), camera {setup.get('image_size')} px at 45 deg, seed {setup.get('seed')}"
          + (f", photos rendered by {setup['renderer']}" if setup.get("renderer", "raster") != "raster" else "") + ").", ""]
    L += ["Layers: " + ", ".join(f"{t} {s.n_failed[t]}" + (f" ({s.n_prints[t]} print{'s' if s.n_prints[t] != 1 else ''})" if t in s.n_prints else "")
                                 for t in s.types) + f", clean {s.n_clean}."
          + (" The failed layers of one print share its one failure: a type with fewer than 5 prints has no AUROC "
             "to speak of." if any(n < 5 for n in s.n_prints.values()) else ""), ""]
    L += ["## Recommendation", ""]
    L += [f"- measure **{names[r]}**, block threshold **T_S = {s.thresholds[j]:.2f}**, "
          f"pause when a% > **{100 * s.pause_ratio[r]:.1f} %** (on 2 consecutive layers in the monitor).",
          "- chosen as the (measure, T_S) pair with the highest mean detection rate over the failure types at a "
          "pause ratio of 1.1 x the highest a% seen on any clean layer (so the sample has no false alarm); "
          "ties broken by worst-type AUROC.", ""]
    return L


def _targets(s: Summary, clean_run: dict | None) -> list[str]:
    """The targets table (recommended setting, and the whole clean prints when run)."""
    r, j = s.rec_metric, s.rec_t
    L = ["## Targets", "", "| target | goal | measured (recommended setting) | met |", "|---|---|---|---|"]
    aucs = s.auc[r, :, j]
    ious = s.iou[r]
    L.append(f"| AUROC per type | >= 0.95 | min {np.nanmin(aucs):.3f} ({', '.join(f'{t} {a:.2f}' for t, a in zip(s.types, aucs, strict=True))}) "
             f"| {'yes' if np.nanmin(aucs) >= 0.95 else 'no'} |")
    okiou = ious[np.isfinite(ious)]
    L.append(f"| localisation IoU, failures >= 5 mm | >= 0.5 | {', '.join(f'{t} {_fmt(v)}' for t, v in zip(s.types, ious, strict=True))} "
             f"| {'yes' if okiou.size and okiou.min() >= 0.5 else 'no'} |")
    L.append(f"| false alarms / 1000 clean layers | <= 1 | {s.fa_rate[r]:.1f} in {s.n_clean} clean layers "
             f"(95 % upper bound {s.fa_upper:.0f}; the sample is too small to show <= 1) | not shown |")
    if clean_run:
        n, prints = clean_run["layers"], clean_run["prints"]
        setting = f" ({clean_run['setting']})" if clean_run.get("setting") else ""
        fa = clean_run["layer_alarms"]
        L.append(_rate_row(f"false alarms / 1000 clean layers, {prints} whole clean prints{setting}", fa, n,
                           f"{fa} layers above the pause ratio with the minimum area in {n}{_ratio_only(clean_run)}; "
                           f"{clean_run['pauses']} pauses with the 2-layer rule"))
        if "policy_alarms" in clean_run:  # what the monitor would actually raise (notify or pause)
            pa = clean_run["policy_alarms"]
            L.append(_rate_row("alerts raised by the monitor's policy / 1000 clean layers", pa, n,
                               f"{pa} notify/pause decisions in {n} layers: ratio, minimum area, growth and "
                               "outside rules"))
        npause = clean_run["pauses"]
        L.append(_rate_row("false pauses / 1000 clean layers (the monitor's policy stops a clean print)", npause, n,
                           f"{npause} pauses in {n} layers of {prints} clean prints", bound_digits=2))
        if clean_run.get("outside_layers") is not None:
            no = clean_run["outside_layers"]
            L.append(_rate_row("clean layers with a change beside the print (scene channel) / 1000", no, n,
                               f"{no} of {n}; largest {clean_run.get('max_outside_mm2', 0.0):.1f} mm^2"))
    L.append(f"| clean printed-area blocks with cosine > 0.7 | >= 95 % | {_fmt(s.clean_block_share, True)} % "
             f"({_fmt(s.clean_flat_share, True)} % of the blocks are featureless in both images and match by rule; "
             f"{_fmt(s.clean_textured_share, True)} % of the others are above 0.7) "
             f"| {'yes' if s.clean_block_share >= 0.95 else 'no'} |")
    L += ["", "Detection at the recommended pause ratio (share of failed layers above it): "
          + ", ".join(f"{t} {100 * v:.0f} %" for t, v in zip(s.types, s.tpr[r], strict=True)) + ".", ""]
    return L


#: issue 18's targets: AUROC per type (both modes; infill and thin wall in series mode), IoU, displacement
_STRONG_TYPES = ("foreign_body", "spaghetti", "detachment", "layer_shift")
_WEAK_TYPES = ("infill_defect", "thin_wall")


def _mode_targets(m: dict, clean_run: dict | None) -> list[str]:
    """Issue 18's targets table from the per-mode figures (and the whole clean prints when run)."""
    L = ["| target | goal | measured | met |", "|---|---|---|---|"]
    for mode in ("single", "series"):
        if mode not in m:
            continue
        auc = m[mode]["auroc"]
        strong = {t: auc[t] for t in _STRONG_TYPES if t in auc}
        if strong:
            ok = all(np.isfinite(v) and v >= 0.97 for v in strong.values())
            L.append(f"| AUROC {mode} mode: foreign body, spaghetti, detachment, layer shift | >= 0.97 | "
                     + ", ".join(f"{t} {_fmt(v, nd=3)}" for t, v in strong.items()) + f" | {'yes' if ok else 'no'} |")
    if "series" in m:
        weak = {t: m["series"]["auroc"][t] for t in _WEAK_TYPES if t in m["series"]["auroc"]}
        if weak:
            ok = all(np.isfinite(v) and v >= 0.85 for v in weak.values())
            L.append("| AUROC series mode: infill, thin wall | >= 0.85 | "
                     + ", ".join(f"{t} {_fmt(v, nd=3)}" for t, v in weak.items()) + f" | {'yes' if ok else 'no'} |")
        ious = {t: m["series"]["iou"][t] for t in _STRONG_TYPES if t in m["series"]["iou"]}
        ok = all(n and v >= 0.5 for v, n in ious.values())
        L.append("| IoU (failures >= 5 mm; every shift and detachment, series mode) | >= 0.5 | "
                 + ", ".join(f"{t} {_fmt(v)} (n {n})" for t, (v, n) in ious.items()) + f" | {'yes' if ok else 'no'} |")
        err = np.asarray(m["series"]["displacement"].get("layer_shift", []), float)
        if err.size:
            L.append(f"| layer-shift displacement error (series mode) | <= 0.5 mm | median {np.median(err):.2f} mm, "
                     f"{100 * np.mean(err <= 0.5):.0f} % of {err.size} typed layer shifts within 0.5 mm, "
                     f"90th percentile {np.percentile(err, 90):.2f} mm | {'yes' if np.percentile(err, 90) <= 0.5 else 'no'} |")
    if clean_run:
        n = clean_run["layers"]
        L.append(f"| false pauses in >= 3000 clean layers (series mode) | 0 | {clean_run['pauses']} in {n} layers "
                 f"| {'yes' if clean_run['pauses'] == 0 and n >= 3000 else ('no' if clean_run['pauses'] else 'not shown: fewer than 3000 layers')} |")
        rate, up = false_alarm_rate(clean_run["layer_alarms"], n)
        L.append(f"| single-layer alarms (a% above the pause ratio and the minimum area) | <= 1 / 1000 | {rate:.2f} / 1000 "
                 f"({clean_run['layer_alarms']} in {n}; 95 % bound {up:.1f}{_ratio_only(clean_run)}) "
                 f"| {_rate_met(clean_run['layer_alarms'], n)} |")
    return L


def _ratio_only(clean_run: dict) -> str:
    """``"; N with a% alone above the ratio"`` for runs that counted it, else ``""``."""
    if "ratio_layers" not in clean_run:
        return ""
    return f"; {clean_run['ratio_layers']} with a% alone above the ratio, whatever the area"


def _modes(s: Summary, clean_run: dict | None, setup: dict) -> list[str]:
    """The section on single-photo and series modes: targets, AUROC by onset, IoU, confusion matrix, displacement."""
    m = s.modes
    if not m:
        return []
    L = ["## Single-photo and series modes (configured setting)", "",
         "Each simulated photo is judged twice with the configured setting: in **series mode** (one pipeline per "
         "print, fed its photos in order, as the monitor runs: the scene channel compares each photo with the "
         "print's own history, the failure typer sees the previous photo's regions) and in **single-photo mode** "
         "(the pipeline forgets the print before every photo: rendered reference and empty-bed photo only). "
         "The layer score is the whole-view score: a% (eq. 5) plus, over the printed area, the area changed "
         "beside the printed layer and the failing blocks beside the footprint of a region typed as a moved "
         "part (layer shift, detachment).", ""]
    L += _mode_targets(m, clean_run) + [""]
    for mode in ("single", "series"):
        if mode not in m:
            continue
        f = m[mode]
        types = list(f["auroc"])
        depths = sorted({d for rows in f["since"].values() for d, _, _ in rows})
        L += [f"### {mode} mode", "", f"Clean photos: {f['n_clean']}; photos the pipeline refused: {f['errors']}.", "",
              "AUROC by layers since the failure's onset (n in brackets; -1 is the layer before it, "
              "a clean negative, not listed):", "",
              "| type | all | " + " | ".join(f"+{d}" for d in depths) + " | IoU >= 5 mm (n) |",
              "|---|---:|" + "---:|" * len(depths) + "---:|"]
        for t in types:
            by = {d: (n, a) for d, n, a in f["since"][t]}
            v, n = f["iou"][t]
            L.append(f"| {type_label(t, setup)} | {_fmt(f['auroc'][t], nd=3)} | "
                     + " | ".join(f"{_fmt(by[d][1])} ({by[d][0]})" if d in by else "" for d in depths)
                     + f" | {_fmt(v)} ({n}) |")
        cols = f["kinds"]
        L += ["", "Failure type confusion (rows: the simulated failure; columns: the kind of the region covering "
              "most of it; `missed`: no region covers it):", "",
              "| true \\ typed | " + " | ".join(cols) + " | correct |", "|---|" + "---:|" * (len(cols) + 1)]
        for t in types:
            row = f["confusion"][t]
            tot = sum(row.values())
            found = tot - row.get("missed", 0)
            L.append(f"| {type_label(t, setup)} | " + " | ".join(str(row[c]) for c in cols)
                     + f" | {_fmt(row.get(t, 0) / found if found else float('nan'), True)} % of {found} found |")
        for t, err in f["displacement"].items():
            e = np.asarray(err, float)
            if e.size:
                L.append(f"\n{t} displacement error (typed regions reporting one): median {np.median(e):.2f} mm, "
                         f"{100 * np.mean(e <= 0.5):.0f} % within 0.5 mm, n {e.size}.")
        L.append("")
    if clean_run and clean_run.get("parts"):
        L += ["Whole clean prints by part (series mode, configured setting):", "",
              "| part | prints | layers | single-layer alarms | a% alone above the ratio | policy alerts | pauses "
              "| layers with a change beside the print |",
              "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for name, c in clean_run["parts"].items():
            L.append(f"| {name} | {c['prints']} | {c['layers']} | {c['layer_alarms']} | {c.get('ratio_layers', '')} "
                     f"| {c['policy_alarms']} | {c['pauses']} | {c['outside_layers']} |")
        L.append("")
    return L


def _configured(configured: dict | None, setup: dict) -> list[str]:
    """The configured setting's own section (empty without it)."""
    L: list[str] = []
    if configured:
        c = configured
        L += ["## The configured setting on this sample", "",
              f"What a job on this part runs with unless its file says otherwise: **{c['metric']}**, "
              f"T_S = {c['threshold']:.2f}, pause when a% > {100 * c['pause_ratio']:.1f} % (the recommendation above "
              f"is what suits this sample best). Clean layers above the pause ratio: {c['clean_above']} of "
              f"{c['n_clean']} (highest clean a% {_fmt(100 * c['max_clean'], nd=1)} %).", "",
              "| type | layers | AUROC | above the pause ratio | IoU (>= 5 mm) |", "|---|---:|---:|---:|---:|"]
        for t, (n, auc_t, det_t, iou_t) in c["types"].items():
            L.append(f"| {type_label(t, setup)} | {n} | {_fmt(auc_t)} | {100 * det_t:.0f} % | {_fmt(iou_t)} |")
        L.append("")
        if "whole_view" in c:
            L += ["With the scene channel (the change beside the printed layer added to S_A, over S_P): AUROC "
                  + ", ".join(f"{t} {_fmt(v)}" for t, v in c["whole_view"].items())
                  + f"; clean layers with any change beside the print: {c['clean_outside']} of {c['n_clean']}.", ""]
    return L


def _per_measure(s: Summary) -> list[str]:
    """The per-measure tables: AUROC, by depth and surface, largest region, a% and DP, IoU, pause ratios."""
    names = s.metrics
    L = ["## Per measure (each at its own best T_S)", "",
          "| measure | T_S | mean a% clean | " + " | ".join(f"AUROC {t}" for t in s.types) + " | min AUROC |",
          "|---|---:|---:|" + "---:|" * (len(s.types) + 1)]
    for m, n in enumerate(names):
        bt = s.best_t[m]
        a = s.auc[m, :, bt]
        L.append(f"| {n} | {s.thresholds[bt]:.2f} | {100 * s.a_clean[m]:.1f} | "
                 + " | ".join(_fmt(v) for v in a) + f" | {_fmt(np.nanmin(a))} |")
    if s.auc_since:
        depths = sorted({d for rows in s.auc_since.values() for d, _, _ in rows})
        L += ["", "AUROC of the recommended setting by layers printed since the failure's onset (patch failures "
              "deepen layer by layer; n in brackets):", "",
              "| type | " + " | ".join(f"+{d}" for d in depths) + " |", "|---|" + "---:|" * len(depths)]
        for t, rows in s.auc_since.items():
            by = {d: (n, a) for d, n, a in rows}
            L.append(f"| {t} | " + " | ".join(f"{_fmt(by[d][1])} ({by[d][0]})" if d in by else "" for d in depths) + " |")
    if s.auc_surface:
        L += ["", "AUROC of the recommended setting by what the plan prints where the failure is (majority of the "
              "layer's segments inside the failed region: solid, top or bridge infill / sparse infill / walls / "
              "nothing, beside the part; n in brackets). Sparse infill repeats from layer to layer, so a patch missing "
              "from it shows the same lines a layer lower; a patch missing from a solid layer shows the layer below:",
              "", "| type | solid | sparse | walls | nothing |", "|---|---:|---:|---:|---:|"]
        for t, rows in s.auc_surface.items():
            by = {c: (n, a) for c, n, a in rows}
            L.append(f"| {t} | " + " | ".join(f"{_fmt(by[c][1])} ({by[c][0]})" if c in by else ""
                                               for c in ("solid", "sparse", "walls", "none")) + " |")
    L += ["", "AUROC with the area of the largest anomalous region (mm^2) as the layer score instead of a% "
          "(same T_S; local defects on large layers are not diluted by the layer's area):", "",
          "| measure | " + " | ".join(f"AUROC {t}" for t in s.types) + " | min |", "|---|" + "---:|" * (len(s.types) + 1)]
    for m, n in enumerate(names):
        L.append(f"| {n} | " + " | ".join(_fmt(v) for v in s.auc_region[m]) + f" | {_fmt(np.nanmin(s.auc_region[m]))} |")
    L += ["", "| measure | " + " | ".join(f"a% {t}" for t in s.types) + " | " + " | ".join(f"DP {t}" for t in s.types) + " |",
          "|---|" + "---:|" * (2 * len(s.types))]
    for m, n in enumerate(names):
        L.append(f"| {n} | " + " | ".join(_fmt(v, True) for v in s.a_failed[m]) + " | "
                 + " | ".join(_fmt(v, nd=1) for v in s.dp[m]) + " |")
    L += ["", "Localisation: IoU (failures >= 5 mm) at the operating T_S / best over all T_S / all sizes at the operating T_S.", "",
          "| measure | " + " | ".join(f"IoU {t}" for t in s.types) + " |", "|---|" + "---:|" * len(s.types)]
    for m, n in enumerate(names):
        L.append(f"| {n} | " + " | ".join(f"{_fmt(a)} / {_fmt(b)} / {_fmt(c)}" for a, b, c in
                                          zip(s.iou[m], s.iou_best[m], s.iou_all[m], strict=True)) + " |")
    L += ["", "| measure | pause a% | false alarms/1000 | "
          + " | ".join(f"TPR {t}" for t in s.types) + " |", "|---|" + "---:|" * (len(s.types) + 2)]
    for m, n in enumerate(names):
        L.append(f"| {n} | {100 * s.pause_ratio[m]:.1f} | "
                 f"{s.fa_rate[m]:.1f} | " + " | ".join(_fmt(v) for v in s.tpr[m]) + " |")
    return L


def write_report(s: Summary, out: str | Path, setup: dict, seconds: float, notes: list[str] | None = None,
                 clean_run: dict | None = None, configured: dict | None = None) -> Path:
    """Write ``report.md`` and the charts into ``out``; returns the report path.

    ``clean_run`` is the output of :func:`~layerwatch.evaluate.harness.clean_false_alarms`
    (whole clean prints under the configured setting, named by its ``"setting"`` key),
    reported with the targets;
    ``configured`` that of :func:`~layerwatch.evaluate.summary.at_setting` for the
    setting the job would run with (its own section).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = _charts(s, out)
    L = _header(s, setup, seconds) + _targets(s, clean_run) + _modes(s, clean_run, setup) + _configured(configured, setup) + _per_measure(s)
    L += _DEFINITIONS_AND_LIMITS
    L += ["## Charts", ""] + [f"![{f}]({f})" for f in files] + [""]
    L += ["## Set-up", "", "```", *(f"{k}: {v}" for k, v in setup.items()), "```", ""]
    if notes:
        L += ["## Notes and limits", "", *(f"- {n}" for n in notes), ""]
    path = out / "report.md"
    path.write_text("\n".join(L))
    return path


def rich_table(s: Summary):
    """A rich Table of the per-type figures of every measure (best T_S each)."""
    tab = Table(title="AUROC per failure type (each measure at its best T_S)")
    tab.add_column("measure")
    tab.add_column("T_S", justify="right")
    for t in s.types:
        tab.add_column(t[:12], justify="right")
    tab.add_column("min", justify="right")
    tab.add_column("IoU mean", justify="right")
    for m, n in enumerate(s.metrics):
        bt = s.best_t[m]
        a = s.auc[m, :, bt]
        style = "bold green" if m == s.rec_metric else None
        iou = s.iou[m][np.isfinite(s.iou[m])]
        tab.add_row(n, f"{s.thresholds[bt]:.2f}", *(_fmt(v) for v in a), _fmt(np.nanmin(a)),
                    _fmt(iou.mean() if iou.size else np.nan), style=style)
    return tab
