"""The PDF page layout: A4, headings, key-value blocks, tables, figures, a footer on every page.

ReportLab: BSD-licensed and maintained since 2000, its Platypus layout flows sections and splits
long tables across pages (header row repeated) by itself, and it embeds TrueType fonts.
The font is matplotlib's DejaVu Sans, embedded: a label in any script prints, and the archived
PDF does not depend on the reader's fonts.
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path
from xml.sax.saxutils import escape

from foamlab import FoamlabError

MARGIN_MM = 16.0
FONT, BOLD, MONO = "DejaVuSans", "DejaVuSans-Bold", "DejaVuSansMono"


def _fonts() -> None:
    from matplotlib import get_data_path  # noqa: PLC0415
    from reportlab.pdfbase import pdfmetrics  # noqa: PLC0415
    from reportlab.pdfbase.ttfonts import TTFont  # noqa: PLC0415

    if FONT in pdfmetrics.getRegisteredFontNames():
        return
    ttf = Path(get_data_path()) / "fonts" / "ttf"
    for name in (FONT, BOLD, MONO):
        pdfmetrics.registerFont(TTFont(name, str(ttf / f"{name}.ttf")))
    pdfmetrics.registerFontFamily(FONT, normal=FONT, bold=BOLD, italic=FONT, boldItalic=BOLD)


def text(value) -> str:
    """Plain text made safe for a Paragraph (its markup is XML)."""
    return escape(str(value))


class Document:
    """Collects flowables section by section and writes the PDF (atomically)."""

    def __init__(self, title: str, footer: str, subject: str = "") -> None:
        from reportlab.lib import colors  # noqa: PLC0415
        from reportlab.lib.styles import ParagraphStyle, getSampleStyleSheet  # noqa: PLC0415

        _fonts()
        self.title, self.footer, self.subject = title, footer, subject
        self.colors = colors
        base = getSampleStyleSheet()
        self.styles = {
            "title": ParagraphStyle("t", parent=base["Title"], fontName=BOLD, fontSize=16, spaceAfter=4),
            "h": ParagraphStyle("h", parent=base["Heading2"], fontName=BOLD, fontSize=12.5,
                                spaceBefore=9, spaceAfter=4),
            "p": ParagraphStyle("p", parent=base["BodyText"], fontName=FONT, fontSize=9, leading=11.5),
            "small": ParagraphStyle("s", parent=base["BodyText"], fontName=FONT, fontSize=7.5, leading=9,
                                    textColor=colors.HexColor("#444444")),
            "cell": ParagraphStyle("c", parent=base["BodyText"], fontName=FONT, fontSize=8, leading=9.5),
            "mono": ParagraphStyle("m", parent=base["BodyText"], fontName=MONO, fontSize=8, leading=10),
            "mono-small": ParagraphStyle("ms", parent=base["BodyText"], fontName=MONO, fontSize=6.5, leading=9),
        }
        self.story: list = []

    @property
    def width(self) -> float:
        from reportlab.lib.pagesizes import A4  # noqa: PLC0415
        from reportlab.lib.units import mm  # noqa: PLC0415

        return A4[0] - 2 * MARGIN_MM * mm

    # -- content ------------------------------------------------------------------------
    def heading(self, title: str) -> None:
        from reportlab.platypus import Paragraph  # noqa: PLC0415

        self.story.append(Paragraph(text(title), self.styles["h"]))

    def paragraph(self, markup: str, style: str = "p") -> None:
        """`markup` is already escaped (build it with text())."""
        from reportlab.platypus import Paragraph  # noqa: PLC0415

        self.story.append(Paragraph(markup, self.styles[style]))

    def fields(self, items: list[tuple[str, str]], mono: tuple[str, ...] = ()) -> None:
        """A two-column block of label and value (values in `mono` keys use the fixed font)."""
        from reportlab.platypus import Paragraph  # noqa: PLC0415

        rows = [[Paragraph(f"<b>{text(k)}</b>", self.styles["cell"]),
                 Paragraph(text(v), self.styles["mono" if k in mono else "cell"])] for k, v in items]
        self._table(rows, [0.24 * self.width, 0.76 * self.width], header=False)

    def table(self, header: list[str], rows: list[list], widths: list[float] | None = None,
              bold_rows: int = 0, mono: tuple[int, ...] = ()) -> None:
        """A table with a header row (repeated on each page); widths are fractions of the page;
        columns in `mono` in a small fixed font (hashes stay on one line)."""
        from reportlab.platypus import Paragraph  # noqa: PLC0415

        def cell(v, bold=False, style="cell"):
            return Paragraph(f"<b>{text(v)}</b>" if bold else text(v), self.styles[style])

        n = len(rows)
        body = [[cell(h, True) for h in header]]
        body += [[cell(v, i >= n - bold_rows, "mono-small" if j in mono else "cell") for j, v in enumerate(row)]
                 for i, row in enumerate(rows)]
        cols = [w * self.width for w in widths] if widths else None
        self._table(body, cols, header=True)

    def _table(self, rows, widths, header: bool) -> None:
        from reportlab.platypus import Table, TableStyle  # noqa: PLC0415

        c = self.colors
        style = [("GRID", (0, 0), (-1, -1), 0.25, c.HexColor("#bbbbbb")),
                 ("VALIGN", (0, 0), (-1, -1), "TOP"),
                 ("TOPPADDING", (0, 0), (-1, -1), 1.5), ("BOTTOMPADDING", (0, 0), (-1, -1), 1.5),
                 ("LEFTPADDING", (0, 0), (-1, -1), 3), ("RIGHTPADDING", (0, 0), (-1, -1), 3)]
        if header:
            style.append(("BACKGROUND", (0, 0), (-1, 0), c.HexColor("#e8e8e8")))
        t = Table(rows, colWidths=widths, repeatRows=1 if header else 0, hAlign="LEFT")
        t.setStyle(TableStyle(style))
        self.story.append(t)

    def figure(self, png: Path | None, caption: str = "") -> None:
        from reportlab.lib.utils import ImageReader  # noqa: PLC0415
        from reportlab.platypus import Image, KeepTogether, Paragraph, Spacer  # noqa: PLC0415

        if png is None:
            return
        w, h = ImageReader(str(png)).getSize()
        width = self.width
        height = width * h / w
        if height > 0.55 * width * 1.414:             # a tall figure: keep it to ~55 % of the page
            height = 0.55 * width * 1.414
            width = height * w / h
        parts = [Spacer(1, 3), Image(str(png), width=width, height=height)]
        if caption:
            parts.append(Paragraph(text(caption), self.styles["small"]))
        self.story.append(KeepTogether(parts))

    def page_break(self) -> None:
        from reportlab.platypus import PageBreak  # noqa: PLC0415

        self.story.append(PageBreak())

    # -- output -------------------------------------------------------------------------
    def write(self, out: Path) -> Path:
        from reportlab.lib.pagesizes import A4  # noqa: PLC0415
        from reportlab.lib.units import mm  # noqa: PLC0415
        from reportlab.platypus import SimpleDocTemplate  # noqa: PLC0415
        from reportlab.platypus.doctemplate import LayoutError  # noqa: PLC0415

        footer = self.footer

        def on_page(canvas, doc):
            canvas.saveState()
            canvas.setFont(FONT, 7)
            canvas.setFillGray(0.35)
            canvas.drawString(MARGIN_MM * mm, 9 * mm, footer)
            canvas.drawRightString(A4[0] - MARGIN_MM * mm, 9 * mm, f"page {doc.page}")
            canvas.restoreState()

        tmp = out.with_name(out.name + ".tmp")
        doc = SimpleDocTemplate(str(tmp), pagesize=A4, leftMargin=MARGIN_MM * mm, rightMargin=MARGIN_MM * mm,
                                topMargin=MARGIN_MM * mm, bottomMargin=(MARGIN_MM + 4) * mm,
                                title=self.title, author="foamlab", subject=self.subject,
                                creator="foamlab report", invariant=False,
                                creationDate=_dt.datetime.now().astimezone())
        try:
            doc.build(list(self.story), onFirstPage=on_page, onLaterPages=on_page)
            tmp.replace(out)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise FoamlabError(f"{out}: cannot write the report ({exc.strerror or exc})") from None
        except LayoutError as exc:        # a block taller than a page: say so, leave no half file
            tmp.unlink(missing_ok=True)
            raise FoamlabError(f"{out}: the report could not be laid out ({str(exc).splitlines()[0]})") from None
        return out
