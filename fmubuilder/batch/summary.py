"""The batch's summary: one row per case, from its record and its report.json, written as
summary.csv (for tools), summary.md and summary.html (for people, linking each case's report).

Per case: its status (ok, failed, skipped: done by an earlier run with the same inputs, pending:
not run yet), what the diagnosis found (the state derivative it traced the effect to, or none),
what was shipped, the test gain (the declared FMU's test MSE over the shipped model's, geometric
mean over the signals), the test score (the shipped model's test MSE over the noise variance, the
same mean; the declared FMU's when nothing was shipped; 1 is the noise floor), the time, and a
failure's one-line reason.
"""
from __future__ import annotations

import csv
import html
import io
from pathlib import Path

from ..files import write_atomically
from .case import REPORT_NAME

COLUMNS = ("name", "status", "found", "shipped", "test_gain", "test_score", "seconds", "reason", "report")
TITLES = {"name": "case", "status": "status", "found": "found", "shipped": "shipped", "test_gain": "test gain",
          "test_score": "test / noise", "seconds": "time [s]", "reason": "failure"}
NAMES = ("summary.csv", "summary.md", "summary.html")


def row(name: str, status: str, record: dict | None, report: dict | None) -> dict:
    found = {"name": name, "status": status, "found": "", "shipped": "", "test_gain": None, "test_score": None,
             "seconds": record.get("seconds") if record else None, "reason": (record or {}).get("reason", ""),
             "report": ""}
    if report is not None:
        found.update(_results(report))
        found["report"] = f"{name}/{REPORT_NAME}/report.md"
    return found


def _results(report: dict) -> dict:
    diagnosis = report.get("diagnosis") or {}
    chosen = next((m for m in report.get("models") or [] if m.get("chosen")), None)
    plain = report.get("test_plain_score")
    results = {"found": diagnosis.get("channel") if diagnosis.get("significant") else "none",
               "shipped": chosen["name"] if chosen else "nothing", "test_score": plain}
    if chosen is not None:
        score = chosen.get("test_score")
        results["test_score"] = score
        results["test_gain"] = plain / score if plain is not None and score else None
    return results


def write_summaries(folder: Path, rows: list[dict], title: str) -> None:
    write_atomically(folder / "summary.csv", to_csv(rows))
    write_atomically(folder / "summary.md", to_markdown(rows, title))
    write_atomically(folder / "summary.html", to_html(rows, title))


def counts(rows: list[dict]) -> str:
    """'3 cases: 2 ok, 1 failed'"""
    by_status: dict[str, int] = {}
    for r in rows:
        by_status[r["status"]] = by_status.get(r["status"], 0) + 1
    return f"{len(rows)} case(s): " + ", ".join(f"{n} {status}" for status, n in by_status.items())


def to_csv(rows: list[dict]) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(COLUMNS)
    for r in rows:
        writer.writerow([_plain(r[column]) for column in COLUMNS])
    return buffer.getvalue()


def _plain(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def _short(value, digits: str = ".3g") -> str:
    return "" if value is None else format(value, digits)


def _cells(r: dict) -> list[str]:
    return [r["status"], r["found"], r["shipped"], _short(r["test_gain"]), _short(r["test_score"]),
            _short(r["seconds"], ".0f"), r["reason"]]


LEGEND = ("found: the state derivative the diagnosis traced the effect to; test gain: the declared FMU's test "
          "MSE over the shipped model's; test / noise: the shipped model's (else the declared FMU's) test MSE over "
          "the noise variance, 1 is the noise floor; both geometric means over the signals.")


def to_markdown(rows: list[dict], title: str) -> str:
    lines = [f"# {title}", "", counts(rows) + ".", "", LEGEND, "",
             "| " + " | ".join(TITLES[c] for c in COLUMNS[:-1]) + " |", "|" + "---|" * (len(COLUMNS) - 1)]
    for r in rows:
        name = f"[{r['name']}]({r['report']})" if r["report"] else r["name"]
        cells = [name, *(cell.replace("|", "\\|") for cell in _cells(r))]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def to_html(rows: list[dict], title: str) -> str:
    head = "".join(f"<th>{html.escape(TITLES[c])}</th>" for c in COLUMNS[:-1])
    body = []
    for r in rows:
        name = html.escape(r["name"])
        if r["report"]:
            name = f'<a href="{html.escape(r["report"].removesuffix(".md") + ".html")}">{name}</a>'
        body.append("<tr><td>" + "</td><td>".join([name, *(html.escape(c) for c in _cells(r))]) + "</td></tr>")
    return (f"<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>{html.escape(title)}</title>\n"
            "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse}"
            "td,th{border:1px solid #ccc;padding:.3em .6em;text-align:left}</style></head><body>\n"
            f"<h1>{html.escape(title)}</h1>\n<p>{html.escape(counts(rows))}.</p>\n<p>{html.escape(LEGEND)}</p>\n"
            f"<table>\n<tr>{head}</tr>\n" + "\n".join(body) + "\n</table>\n</body></html>\n")
