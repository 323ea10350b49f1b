"""The report tables' model and renderings: a `Table` (title, columns, rows,
an optional spanning header and notes) written as Markdown, LaTeX, CSV or a
self-contained HTML page, after `prune` left out what was not run.
mogaf.report.tables fills them from metrics.json files.
"""

from __future__ import annotations

import csv
import html
import io
from dataclasses import dataclass, field

from .metrics_files import NO_RESULT

HTML_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<style>
body {{ font-family: sans-serif; margin: 1em; }}
table {{ border-collapse: collapse; }}
th, td {{ border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right; }}
tbody th {{ text-align: left; font-weight: normal; }}
.note {{ font-size: 0.85em; color: #444; }}
figure {{ margin: 0 0 1.5em 0; }}
figcaption {{ font-weight: bold; margin-bottom: 0.3em; }}
video, img {{ max-width: 100%; image-rendering: pixelated; }}
</style></head>
<body>
{body}
</body></html>
"""

# A cell whose result does not exist, among cells that have one.
MISSING = "–"


@dataclass
class Table:
    title: str
    columns: list[str]
    rows: list[list[str]] = field(default_factory=list)
    # Optional spanning header above the columns: (label, span) pairs.
    spans: list[tuple[str, int]] | None = None
    notes: list[str] = field(default_factory=list)
    # The leading columns that name a row (scene, method, ...); the rest hold results.
    keys: int = 0

    def empty_line(self) -> str:
        return f"Nothing to show: {NO_RESULT} in the metrics.json files read holds what this table reports."

    def prune(self) -> Table:
        """Leave out what was not run: rows whose result cells are all missing,
        then result columns missing in every row (and a spanning header whose
        columns all went). A table with no row keeps its columns (the CSV header)."""
        self.rows = [r for r in self.rows if any(c != MISSING for c in r[self.keys :])]
        if not self.rows:
            return self
        keep = [i for i in range(len(self.columns)) if i < self.keys or any(r[i] != MISSING for r in self.rows)]
        if self.spans:
            spans, start = [], 0
            for label, span in self.spans:
                kept = sum(1 for i in range(start, start + span) if i in keep)
                if kept:
                    spans.append((label, kept))
                start += span
            self.spans = spans
        self.columns = [self.columns[i] for i in keep]
        self.rows = [[r[i] for i in keep] for r in self.rows]
        return self

    def markdown(self) -> str:
        lines = [f"### {self.title}", ""]
        if not self.rows:
            return "\n".join(lines + [self.empty_line()]) + "\n"
        if self.spans:
            top = [label for label, span in self.spans for _ in range(span)]
            lines.append("| " + " | ".join(top) + " |")
            lines.append("|" + "---|" * len(self.columns))
            lines.append("| " + " | ".join(self.columns) + " |")
        else:
            lines.append("| " + " | ".join(self.columns) + " |")
            lines.append("|" + "---|" * len(self.columns))
        lines += ["| " + " | ".join(r) + " |" for r in self.rows]
        lines += [""] + [f"{n}" for n in self.notes]
        return "\n".join(lines).rstrip() + "\n"

    def latex(self) -> str:
        def esc(s: str) -> str:
            for a, b in (
                ("\\", r"\textbackslash{}"),
                ("&", r"\&"),
                ("%", r"\%"),
                ("_", r"\_"),
                ("#", r"\#"),
                ("↑", r"$\uparrow$"),
                ("↓", r"$\downarrow$"),
                ("δ", r"$\delta$"),
                ("✓", r"\checkmark"),
                ("–", "--"),
            ):
                s = s.replace(a, b)
            return s

        if not self.rows:
            return (
                "\n".join(
                    [
                        r"\begin{table}[t]",
                        r"\centering",
                        f"\\caption{{{esc(self.title)}}}",
                        esc(self.empty_line()),
                        r"\end{table}",
                    ]
                )
                + "\n"
            )
        out = [
            r"\begin{table}[t]",
            r"\centering",
            f"\\caption{{{esc(self.title)}}}",
            r"\resizebox{\linewidth}{!}{",
            r"\begin{tabular}{" + "l" * 1 + "c" * (len(self.columns) - 1) + "}",
            r"\toprule",
        ]
        if self.spans:
            out.append(
                " & ".join(
                    f"\\multicolumn{{{span}}}{{c}}{{{esc(label)}}}" if span > 1 else esc(label)
                    for label, span in self.spans
                )
                + r" \\"
            )
        out.append(" & ".join(esc(c) for c in self.columns) + r" \\")
        out.append(r"\midrule")
        out += [" & ".join(esc(c) for c in r) + r" \\" for r in self.rows]
        out += [r"\bottomrule", r"\end{tabular}", "}"]
        out += [r"\par{\footnotesize " + esc(n) + "}" for n in self.notes]
        out.append(r"\end{table}")
        return "\n".join(out) + "\n"

    def html(self) -> str:
        """A self-contained page (the Snakemake report shows HTML inline, Markdown only as a download)."""
        esc = html.escape
        parts = [f"<h3>{esc(self.title)}</h3>"]
        if not self.rows:
            parts.append(f"<p>{esc(self.empty_line())}</p>")
        else:
            head = []
            if self.spans:
                head.append(
                    "<tr>" + "".join(f'<th colspan="{n}">{esc(label)}</th>' for label, n in self.spans) + "</tr>"
                )
            head.append("<tr>" + "".join(f"<th>{esc(c)}</th>" for c in self.columns) + "</tr>")
            body = [
                "<tr>"
                + "".join(
                    f"<{'th' if i < self.keys else 'td'}>{esc(c)}</{'th' if i < self.keys else 'td'}>"
                    for i, c in enumerate(r)
                )
                + "</tr>"
                for r in self.rows
            ]
            parts.append(f"<table><thead>{''.join(head)}</thead><tbody>{''.join(body)}</tbody></table>")
            parts += [f"<p class=note>{esc(n)}</p>" for n in self.notes]
        return HTML_PAGE.format(title=esc(self.title), body="\n".join(parts))

    def csv(self) -> str:
        buf = io.StringIO()
        writer = csv.writer(buf, lineterminator="\n")
        writer.writerow(self.columns)
        writer.writerows([c if i < self.keys or c != MISSING else "" for i, c in enumerate(r)] for r in self.rows)
        return buf.getvalue()
