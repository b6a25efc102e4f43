"""The static HTML report of a rendered CAM run: one file, relative image links, inline SVG timelines, no network."""

from __future__ import annotations

import dataclasses
import math
import pathlib
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any

from openpi_cam.cam.run_format import RELIANCE_PROMPT, StepMeta
from openpi_cam.viz.evidence import CHECK_COLUMNS, SUMMARY_COLUMNS, MapEvidence, check_rows, summary_rows
from openpi_cam.viz.stats import StepStats, aggregate, camera_names
from openpi_cam.viz.text import escape, html_table, number, percent

_PALETTE = ("#4e9af1", "#f28e2b", "#59a14f", "#e15759", "#b07aa1", "#76b7b2", "#edc948", "#ff9da7")


@dataclasses.dataclass(frozen=True)
class StepAssets:
    """Paths relative to the output directory."""

    panel: str
    thumb: str
    overlays: dict[str, str]


@dataclasses.dataclass
class RenderResult:
    out_dir: pathlib.Path
    steps: dict[int, StepAssets]
    videos: dict[str, dict[str, str]]  # connection -> {"mp4": path, "gif": path}
    stats: list[StepStats]
    report: pathlib.Path | None = None


@dataclasses.dataclass(frozen=True)
class Flag:
    seq: int
    reason: str


@dataclasses.dataclass(frozen=True)
class Failure:
    """A step whose generation was malformed (upstream answered with its zero-action fallback); its maps explain
    the failure (target `generated-tokens`)."""

    seq: int
    connection: str
    step: int
    reason: str
    target: str


def failure_steps(step_meta: Mapping[int, StepMeta]) -> list[Failure]:
    """The failure steps among `step_meta` (seq -> the step's metadata, or the manifest's index entries read as
    such), in seq order."""
    return [
        Failure(
            seq=int(seq),
            connection=meta.connection or "",
            step=-1 if meta.step is None else meta.step,
            reason=meta.malformed,
            target=meta.target,
        )
        for seq, meta in sorted(step_meta.items())
        if meta.malformed is not None
    ]


def usual_camera(stats: Sequence[StepStats]) -> str | None:
    """The camera most often dominant over these steps."""
    counts = Counter(st.dominant for st in stats if st.dominant is not None)
    return counts.most_common(1)[0][0] if counts else None


def flag_steps(stats: Sequence[StepStats], score_drop: float = 0.3) -> list[Flag]:
    """Steps where attention left the connection's usual camera, or the score fell by more than `score_drop`
    (a fraction) from the connection's previous step."""
    flags: list[Flag] = []
    for conn_stats in by_connection(stats).values():
        usual = usual_camera(conn_stats)
        prev_score = math.nan
        for st in conn_stats:
            if usual is not None and st.dominant is not None and st.dominant != usual:
                flags.append(Flag(st.seq, f"attention moved from {usual} to {st.dominant}"))
            if prev_score > 0 and st.score < (1.0 - score_drop) * prev_score:
                flags.append(Flag(st.seq, f"score dropped {100 * (1 - st.score / prev_score):.0f}%"))
            prev_score = st.score
    return sorted(flags, key=lambda f: f.seq)


def by_connection(stats: Sequence[StepStats]) -> dict[str, list[StepStats]]:
    groups: dict[str, list[StepStats]] = {}
    for st in stats:
        groups.setdefault(st.connection, []).append(st)
    return groups


def _polyline(xs: Sequence[float], ys: Sequence[float], color: str, dash: str = "") -> str:
    """Polylines broken at missing (NaN) values."""
    runs: list[list[str]] = [[]]
    for x, y in zip(xs, ys, strict=True):
        if y is None or math.isnan(y):
            runs.append([])
        else:
            runs[-1].append(f"{x:.1f},{y:.1f}")
    style = f' stroke-dasharray="{dash}"' if dash else ""
    return "".join(
        f'<polyline points="{" ".join(r)}" fill="none" stroke="{color}" stroke-width="1.5"{style}/>'
        if len(r) > 1
        else f'<circle cx="{r[0].split(",")[0]}" cy="{r[0].split(",")[1]}" r="2" fill="{color}"/>'
        for r in runs
        if r
    )


def timeline_svg(
    title: str,
    steps: Sequence[StepStats],
    series: Sequence[tuple[str, str, Sequence[float], str]],
    flags: Mapping[int, list[str]],
    y_range: tuple[float, float] | None = None,
) -> str:
    """A small inline SVG line chart over the connection's steps; flagged steps are clickable red markers.

    `series` holds (label, colour, values, dash pattern). Clicking anywhere over a step jumps to its detail.
    """
    width, height, left, right, top, bottom = 900, 164, 46, 10, 34, 18
    n = len(steps)
    values = [v for _, _, vs, _ in series for v in vs if v is not None and not math.isnan(v)]
    lo, hi = y_range or ((min(values), max(values)) if values else (0.0, 1.0))
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    plot_w, plot_h = width - left - right, height - top - bottom

    def x_of(i: int) -> float:
        return left + (plot_w * (i + 0.5) / n if n else 0)

    def y_of(v: float) -> float:
        return top + plot_h * (1 - (v - lo) / (hi - lo))

    parts = [
        f'<svg class="timeline" viewBox="0 0 {width} {height}" width="{width}" height="{height}" role="img">',
        f'<text x="{left}" y="13" class="t">{escape(title)}</text>',
        f'<rect x="{left}" y="{top}" width="{plot_w}" height="{plot_h}" class="frame"/>',
        f'<text x="{left - 4}" y="{top + 9}" class="ax" text-anchor="end">{hi:.3g}</text>',
        f'<text x="{left - 4}" y="{top + plot_h}" class="ax" text-anchor="end">{lo:.3g}</text>',
    ]
    slot = plot_w / n if n else plot_w
    for i, st in enumerate(steps):
        reasons = flags.get(st.seq)
        cls = "flag" if reasons else "hit"
        tip = f"seq {st.seq}, step {st.step}" + (": " + "; ".join(reasons) if reasons else "")
        parts.append(
            f'<a href="#step-{st.seq}"><rect x="{left + i * slot:.1f}" y="{top}" width="{max(slot, 1):.1f}"'
            f' height="{plot_h}" class="{cls}"><title>{escape(tip)}</title></rect></a>'
        )
    xs = [x_of(i) for i in range(n)]
    legend_x = left
    for label, color, vs, dash in series:
        if all(v is None or math.isnan(v) for v in vs):
            continue  # e.g. a camera masked on the whole connection
        parts.append(_polyline(xs, [math.nan if v is None or math.isnan(v) else y_of(v) for v in vs], color, dash))
        # The legend sits on its own line under the title; 6 px per character fits the 10 px font.
        mark = f'<line x1="{legend_x}" y1="24" x2="{legend_x + 14}" y2="24" stroke="{color}" stroke-width="2"' + (
            f' stroke-dasharray="{dash}"/>' if dash else "/>"
        )
        parts.append(f'{mark}<text x="{legend_x + 18}" y="28" class="lg">{escape(label)}</text>')
        legend_x += 6 * len(label) + 34
    parts.append(
        f'<text x="{left}" y="{height - 4}" class="ax">steps {steps[0].step if n else ""}..'
        f"{steps[-1].step if n else ''}</text>"
    )
    parts.append("</svg>")
    return "".join(parts)


def _connection_section(
    conn: str, steps: Sequence[StepStats], result: RenderResult, flags: Mapping[int, list[str]], cams: list[str]
) -> str:
    colors = {c: _PALETTE[i % len(_PALETTE)] for i, c in enumerate(cams)}

    def col(c: str, field: str) -> list[float]:
        out = []
        for st in steps:
            cs = st.cameras.get(c)
            out.append(math.nan if cs is None else getattr(cs, field))
        return out

    def peak_frac(c: str, axis: int) -> list[float]:
        out = []
        for st in steps:
            cs = st.cameras.get(c)
            out.append(cs.peak[axis] if cs is not None and cs.peak is not None else math.nan)
        return out

    share = timeline_svg(
        "attention share per camera", steps, [(c, colors[c], col(c, "share"), "") for c in cams], flags, (0.0, 1.0)
    )
    peaks = timeline_svg(
        "peak cell per camera (solid: row, dashed: column)",
        steps,
        [
            s
            for c in cams
            for s in ((f"{c} row", colors[c], peak_frac(c, 0), ""), (f"{c} col", colors[c], peak_frac(c, 1), "4 3"))
        ],
        flags,
    )
    score = timeline_svg("score", steps, [("score", "#dddddd", [st.score for st in steps], "")], flags)
    boxed = [c for c in cams if any(not math.isnan(col(c, "nuisance_mass")[i]) for i in range(len(steps)))]
    nuisance = (
        timeline_svg(
            "nuisance mass ratio (map mass outside the client's target box; lower is better)",
            steps,
            [(c, colors[c], col(c, "nuisance_mass"), "") for c in boxed],
            flags,
            (0.0, 1.0),
        )
        if boxed
        else ""
    )
    conn_flags = [(st, flags[st.seq]) for st in steps if st.seq in flags]
    flag_items = "".join(
        f'<li><a href="#step-{st.seq}">seq {st.seq} (step {st.step})</a>: {escape("; ".join(r))}</li>'
        for st, r in conn_flags
    )
    video = result.videos.get(conn)
    media = (
        f'<p><a href="{escape(video["mp4"])}">MP4</a> · <a href="{escape(video["gif"])}">GIF</a></p>'
        f'<video src="{escape(video["mp4"])}" controls loop muted preload="metadata"></video>'
        if video
        else ""
    )
    thumbs = "".join(
        f'<a href="#step-{st.seq}" class="th{" flagged" if st.seq in flags else ""}" title="seq {st.seq}">'
        f'<img src="{escape(result.steps[st.seq].thumb)}" alt="seq {st.seq}" loading="lazy"></a>'
        for st in steps
    )
    return (
        f'<section class="conn" id="conn-{escape(conn)}">'
        f"<h2>connection {escape(conn)} · {len(steps)} steps</h2>{media}"
        f"{share}{peaks}{score}{nuisance}"
        f"<h3>flagged steps ({len(conn_flags)})</h3><ul>{flag_items or '<li>none</li>'}</ul>"
        f'<div class="thumbs">{thumbs}</div></section>'
    )


def _evidence_section(evidence: MapEvidence) -> str:
    """How faithful the drawn kind measured on this run, before any map is shown."""
    table = html_table(SUMMARY_COLUMNS, summary_rows(evidence)) if evidence.cameras else ""
    if evidence.check_summary:
        table += "<p class='dim'>spot checks stored with the steps (live or offline explain)</p>"
        table += html_table(CHECK_COLUMNS, check_rows(evidence))
    facts = []
    if evidence.zero_share is not None:
        facts.append(f"{percent(evidence.zero_share)} of the drawn camera-steps have an all-zero (or all-negative) map")
    ig = evidence.ig_completeness
    if ig:
        facts.append(
            f"IG completeness over {ig['steps']} steps: largest relative error {percent(ig['max_relative_error'])}"
        )
    items = "".join(f"<li>{escape(f)}</li>" for f in facts)
    return (
        f'<section class="evidence" id="evidence" data-status="{escape(evidence.status)}">'
        f"<h2>how faithful are these maps?</h2><p>{escape(evidence.note)}</p>"
        f'<p class="{"warn" if evidence.status == "missing" else "dim"}">{escape(evidence.status_line)}</p>'
        f"{table}<ul>{items}</ul></section>"
    )


def _failures_section(failures: Sequence[Failure]) -> str:
    items = "".join(
        f'<li><a href="#step-{f.seq}">seq {f.seq} (connection {escape(f.connection)}, step {f.step})</a>: '
        f'malformed generation <code class="reason">{escape(f.reason)}</code>, explained with target '
        f'<code class="target">{escape(f.target)}</code></li>'
        for f in failures
    )
    return (
        f'<section class="failures" id="failures"><h2>failures ({len(failures)})</h2>'
        "<p class='dim'>steps whose generation decoded to no actions (the client got upstream's zero-action "
        "fallback); their maps explain what the model generated instead</p>"
        f"<ul>{items or '<li>none</li>'}</ul></section>"
    )


def _step_section(
    st: StepStats,
    meta_cams: list[str],
    assets: Any,
    flags: list[str],
    prev_next: tuple[Any, Any],
    failure: Failure | None = None,
    evidence: MapEvidence | None = None,
) -> str:
    rows = []
    for c in meta_cams:
        cs = st.cameras.get(c)
        if cs is None:
            continue
        peak = f"{cs.peak[0]}, {cs.peak[1]}" if cs.peak else "-"
        shift = "-" if math.isnan(cs.peak_shift) else f"{cs.peak_shift:.2f}"
        entropy = "-" if math.isnan(cs.entropy_norm) else f"{cs.entropy_norm:.3f}"
        link = assets.overlays.get(c)
        name = f'<a href="{escape(link)}">{escape(c)}</a>' if link else escape(c)
        rows.append(
            f"<tr><td>{name}</td><td>{'yes' if cs.valid else 'no'}</td><td>{100 * cs.share:.1f}%</td>"
            f"<td>{entropy}</td><td>{peak}</td><td>{shift}</td>"
            f'<td class="evidence">{escape(evidence.step_line(st.seq, c)) if evidence else "-"}</td>'
            + (f"<td>{_reliance(st, c)}</td>" if st.reliance else "")
            + "</tr>"
        )
    if st.reliance:
        rows.append(f"<tr><td>prompt (emptied)</td>{'<td></td>' * 6}<td>{_reliance(st, RELIANCE_PROMPT)}</td></tr>")
    nav = " ".join(
        f'<a href="#step-{s.seq}">{label}</a>' for s, label in zip(prev_next, ("prev", "next"), strict=True) if s
    )
    warn = f'<p class="warn">{escape("; ".join(flags))}</p>' if flags else ""
    if failure is not None:
        warn = f'<p class="fail">malformed generation: {escape(failure.reason)}</p>' + warn
    return (
        f'<section class="step{" failure" if failure else ""}" id="step-{st.seq}" data-seq="{st.seq}">'
        f"<h3>seq {st.seq} · connection {escape(st.connection)} · step {st.step} · {escape(st.target)} · "
        f"score {st.score:.4g} <small>{nav}</small></h3>{warn}"
        f'<a href="{escape(assets.panel)}"><img class="panel" src="{escape(assets.panel)}" alt="seq {st.seq}"></a>'
        "<table><tr><th>camera</th><th>valid</th><th>share</th><th>entropy (norm.)</th><th>peak (row, col)</th>"
        "<th>peak shift</th><th>top patch's drop / best patch's</th>"
        + ("<th>reliance: score drop / action change without it</th>" if st.reliance else "")
        + "</tr>"
        f"{''.join(rows)}</table>"
        f"<p class='dim'>tokens {escape(' '.join(map(str, st.token_ids)))}</p></section>"
    )


def _reliance(st: StepStats, name: str) -> str:
    """The step's reliance on a camera or its prompt: the explained score's drop and the action chunk's change (root
    mean square, robot units) when it is replaced by the baseline frame (the prompt: emptied)."""
    score, actions = st.reliance.get(f"{name}/reliance_score"), st.reliance.get(f"{name}/reliance_actions")
    return f"{number(score)} / {number(actions)}"


REPORT_STYLE = """
body{background:#18181c;color:#e8e8e8;font:14px/1.4 system-ui,sans-serif;margin:16px 24px}
a{color:#8cb8ff}h1,h2,h3{font-weight:600}table{border-collapse:collapse;margin:6px 0}
td,th{border:1px solid #444;padding:2px 8px;text-align:left}.dim{color:#999}.warn{color:#ff8a80}
.fail{color:#ffb74d}section.failures li{margin:2px 0}
.timeline{display:block;margin:6px 0;background:#202026}.timeline .t{fill:#ccc;font-size:12px}
.timeline .ax,.timeline .lg{font-size:10px;fill:#aaa}.timeline .frame{fill:none;stroke:#555}
.timeline .hit{fill:transparent}.timeline .hit:hover{fill:rgba(255,255,255,.08)}
.timeline .flag{fill:rgba(255,90,90,.25)}.timeline .flag:hover{fill:rgba(255,90,90,.5)}
.thumbs{display:flex;flex-wrap:wrap;gap:4px}.th img{display:block;border:2px solid transparent}
.th.flagged img{border-color:#ff5a5a}img.panel{max-width:100%}video{max-width:900px;width:100%;display:block}
dl{display:grid;grid-template-columns:max-content auto;gap:2px 12px}dt{color:#999}dd{margin:0}
section.step{border-top:1px solid #333;padding-top:8px;margin-top:12px}
"""

# Marks each step whose panel image actually decoded, so a headless browser's DOM dump can prove it.
_SCRIPT = """
window.addEventListener('load',function(){var n=0;document.querySelectorAll('section.step').forEach(function(s){
var i=s.querySelector('img.panel');if(i&&i.complete&&i.naturalWidth>0){s.setAttribute('data-rendered','1');n++;}});
document.body.setAttribute('data-rendered-steps',String(n));});
"""


def write_report(
    result: RenderResult,
    manifest: Mapping[str, Any],
    *,
    map_label: str,
    norm: str,
    score_drop: float = 0.3,
    step_meta: Mapping[int, StepMeta] | None = None,
    evidence: MapEvidence | None = None,
) -> pathlib.Path:
    """Writes `index.html` into the render directory and returns its path.

    `evidence` (how faithful the drawn kind measured on this run, `viz.evidence`) opens the report and gives each
    step's figure beside its cameras. Failure steps (malformed generations) are listed first, from `step_meta`
    (seq -> the step's metadata, which names them in every schema version) or else from the manifest's index entries
    (schema 2 names them there too)."""
    stats = result.stats
    rendered = {st.seq for st in stats}
    if step_meta is None:
        entries = [e for e in manifest.get("steps", []) if isinstance(e, dict) and isinstance(e.get("seq"), int)]
        step_meta = {e["seq"]: StepMeta.from_json(e) for e in entries}
    failures = [f for f in failure_steps(step_meta) if f.seq in rendered]
    failure_of = {f.seq: f for f in failures}
    cams = camera_names(stats)
    flag_map: dict[int, list[str]] = {}
    for f in flag_steps(stats, score_drop):
        flag_map.setdefault(f.seq, []).append(f.reason)
    summary = aggregate(stats)
    run_id = manifest.get("run_id", result.out_dir.name)
    info = {
        "started": manifest.get("started_at"),
        "checkpoint": manifest.get("checkpoint"),
        "steps": f"{summary['steps']} on {summary['connections']} connection(s)",
        "failures": f"{len(failures)} of {summary['steps']} steps (malformed generations, listed first)",
        "normalisation": f"per {norm}",
        "flagged": f"attention left the connection's usual camera, or the score fell by more than "
        f"{100 * score_drop:.0f}% from the previous step",
    }
    info_html = "".join(f"<dt>{escape(k)}</dt><dd>{escape(v)}</dd>" for k, v in info.items() if v is not None)
    cam_rows = "".join(
        f"<tr><td>{escape(c)}</td><td>{a['valid_steps']}</td><td>{percent(a['mean_share'])}</td>"
        f"<td>{number(a['mean_entropy_norm'])}</td><td>{percent(a['peak_stay_rate'])}</td>"
        f"<td>{number(a['mean_peak_shift'])}</td><td>{a['dominant_steps']}</td></tr>"
        for c, a in summary["cameras"].items()
    )
    groups = by_connection(stats)
    sections = "".join(_connection_section(conn, steps, result, flag_map, cams) for conn, steps in groups.items())
    step_html = []
    for steps in groups.values():
        for i, st in enumerate(steps):
            neighbours = (steps[i - 1] if i > 0 else None, steps[i + 1] if i + 1 < len(steps) else None)
            step_html.append(
                _step_section(
                    st,
                    meta_cams=cams,
                    assets=result.steps[st.seq],
                    flags=flag_map.get(st.seq, []),
                    prev_next=neighbours,
                    failure=failure_of.get(st.seq),
                    evidence=evidence,
                )
            )
    body = (
        f"<h1>CAM run {escape(run_id)}: {escape(map_label)} maps</h1>"
        f"<dl>{info_html}</dl>"
        "<table><tr><th>camera</th><th>valid steps</th><th>mean share</th><th>mean entropy (norm.)</th>"
        f"<th>peak stayed</th><th>mean peak shift (cells)</th><th>dominant in</th></tr>{cam_rows}</table>"
        f"{_evidence_section(evidence) if evidence else ''}{_failures_section(failures)}{sections}"
        f"<h2>steps</h2>{''.join(step_html)}<script>{_SCRIPT}</script>"
    )
    return write_page(result.out_dir / "index.html", f"CAM run {run_id}", body)


def write_page(path: pathlib.Path, title: str, body: str, style: str = REPORT_STYLE) -> pathlib.Path:
    """Writes an HTML page with the reports' head (charset, escaped title, style) around `body` (HTML)."""
    head = f'<head><meta charset="utf-8"><title>{escape(title)}</title><style>{style}</style></head>'
    path.write_text(f'<!doctype html><html lang="en">{head}<body>{body}</body></html>\n', encoding="utf-8")
    return path
