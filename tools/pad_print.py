"""``visland pad print``: a pad design at true scale, as a PDF tiled across pages or as one PNG for
a print shop.

The PDF is written by hand (a few dozen lines of PDF 1.4, no dependency): page sizes are exact
in points (:data:`PAPERS`), the pad lies on the pages at :data:`PT_PER_M` points a metre, and
every page carries a 10 cm scale bar (:data:`SCALE_BAR_PT` = 283.465 pt, drawn as one line in
a ``/ScaleBar`` marked-content sequence) to check the printer printed at 100 %.

Layout: page 1 is the assembly map (the whole pad, shrunk, with the tile grid and page numbers;
the pad's name and size; how to assemble it). Then one page per tile, row by row from the pad's
north-west corner. A tile shows the pad within :data:`MARGIN_PT` of the paper's edge; neighbouring
tiles share an :data:`OVERLAP_PT` strip of the pad. On each page a dashed line runs along the
middle of every shared strip, with registration crosses on it: cut one page along its dashed
line, lay it on its neighbour so that the crosses' halves meet, and tape it. The orientation
(portrait or landscape) with fewer pages is used.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sitl_sim.errors import ConfigError
from sitl_sim.render.pads import PadDesign

__all__ = [
    "MARGIN_PT",
    "OVERLAP_PT",
    "PAPERS",
    "PAPER_NAMES",
    "PT_PER_M",
    "SCALE_BAR_PT",
    "Layout",
    "PrintReport",
    "layout",
    "write_pdf",
    "write_png",
]

PT_PER_M = 72.0 / 0.0254
"""PostScript points per metre (1 pt = 1/72 inch)."""
PAPERS = {
    "a4": (595.28, 841.89),
    "a3": (841.89, 1190.55),
    "letter": (612.0, 792.0),
    "poster": (2383.94, 3370.39),  # A0
}
"""Portrait page sizes in points (width, height)."""
PAPER_NAMES = {"a4": "A4", "a3": "A3", "letter": "Letter", "poster": "A0 poster"}
MARGIN_PT = 0.012 * PT_PER_M
"""Blank border of a tile page (12 mm): most printers cannot print to the edge; the page's
label and scale bar stand in it."""
OVERLAP_PT = 0.010 * PT_PER_M
"""Strip of the pad that two neighbouring tiles share (10 mm)."""
SCALE_BAR_PT = 0.1 * PT_PER_M
"""The scale bar: 10 cm = 283.465 pt."""
PDF_MAX_PX = 4000
"""The pad image in the PDF is at most this many pixels on its longer side (a 4 m pad: 1 mm a
pixel) and at most 100 dpi (0.254 mm a pixel)."""
PNG_MAX_PX = 12000
"""``--png``: the longest side the one image may have (a 4 m pad at 76 dpi)."""


@dataclass(frozen=True)
class Layout:
    """How a pad of ``pad_pt`` (width, height, points) lies on ``paper`` pages."""

    paper: str
    page_pt: tuple[float, float]
    """(width, height) of a page as laid out (landscape: the paper's sides swapped)."""
    landscape: bool
    cols: int
    rows: int
    pad_pt: tuple[float, float]

    @property
    def content_pt(self) -> tuple[float, float]:
        """The pad area of a tile page (inside the margins)."""
        return self.page_pt[0] - 2 * MARGIN_PT, self.page_pt[1] - 2 * MARGIN_PT

    @property
    def step_pt(self) -> tuple[float, float]:
        """From one tile to the next along the pad (content less the shared strip)."""
        cw, ch = self.content_pt
        return cw - OVERLAP_PT, ch - OVERLAP_PT

    @property
    def tiles(self) -> int:
        return self.rows * self.cols

    @property
    def pages(self) -> int:
        """The assembly map and the tiles."""
        return 1 + self.tiles

    def tile_origin_pt(self, row: int, col: int) -> tuple[float, float]:
        """The pad point (east of the west edge, south of the north edge; points) at the top
        left of tile (row, col)'s content area."""
        sx, sy = self.step_pt
        return col * sx, row * sy


def _count(length_pt: float, content_pt: float) -> int:
    if length_pt <= content_pt:
        return 1
    return 1 + math.ceil((length_pt - content_pt) / (content_pt - OVERLAP_PT) - 1e-9)


def layout(size_m: tuple[float, float], paper: str) -> Layout:
    """The tiling of a pad of ``size_m`` (east, north) on ``paper``: the orientation with fewer
    pages (portrait on a tie)."""
    if paper not in PAPERS:
        raise ConfigError(f"--paper: expected one of {sorted(PAPERS)}, got {paper!r}")
    pad = (size_m[0] * PT_PER_M, size_m[1] * PT_PER_M)
    best = None
    for landscape in (False, True):
        w, h = PAPERS[paper][::-1] if landscape else PAPERS[paper]
        cols = _count(pad[0], w - 2 * MARGIN_PT)
        rows = _count(pad[1], h - 2 * MARGIN_PT)
        cand = Layout(paper, (w, h), landscape, cols, rows, pad)
        if best is None or cand.tiles < best.tiles:
            best = cand
    assert best is not None
    return best


@dataclass(frozen=True)
class PrintReport:
    out: Path
    pages: int
    rows: int
    cols: int
    paper: str
    landscape: bool
    image_dpi: float
    """Resolution of the pad's image as printed."""


# --------------------------------------------------------------------------- PDF objects


def _text(s: str) -> bytes:
    """A PDF literal string of printable ASCII."""
    clean = "".join(c if 32 <= ord(c) < 127 else "?" for c in s)
    return (
        b"(" + clean.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)").encode() + b")"
    )


def _num(v: float) -> str:
    s = f"{v:.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


class _Pdf:
    """Objects numbered as added; :meth:`write` adds the catalog, page tree, xref and trailer."""

    def __init__(self) -> None:
        self.objects: list[bytes] = [b"", b""]  # 1: catalog, 2: page tree (filled at the end)
        self.pages: list[int] = []

    def add(self, body: bytes) -> int:
        self.objects.append(body)
        return len(self.objects)

    def stream(self, head: str, data: bytes, compress: bool) -> int:
        if compress:
            data = zlib.compress(data, 9)
            head += " /Filter /FlateDecode"
        return self.add(
            f"<< {head} /Length {len(data)} >>\nstream\n".encode() + data + b"\nendstream"
        )

    def image(self, rgb: np.ndarray) -> int:
        rows, cols = rgb.shape[:2]
        head = (
            f"/Type /XObject /Subtype /Image /Width {cols} /Height {rows} "
            "/ColorSpace /DeviceRGB /BitsPerComponent 8"
        )
        return self.stream(head, np.ascontiguousarray(rgb, dtype=np.uint8).tobytes(), True)

    def page(self, size: tuple[float, float], content: bytes, images: dict[str, int]) -> None:
        stream = self.stream("", content, False)
        xobj = " ".join(f"/{k} {v} 0 R" for k, v in images.items())
        body = (
            f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {_num(size[0])} {_num(size[1])}] "
            f"/Resources << /Font << /F1 3 0 R >> /XObject << {xobj} >> >> "
            f"/Contents {stream} 0 R >>"
        )
        self.pages.append(self.add(body.encode()))

    def write(self, path: Path) -> None:
        self.objects[0] = b"<< /Type /Catalog /Pages 2 0 R >>"
        kids = " ".join(f"{p} 0 R" for p in self.pages)
        self.objects[1] = f"<< /Type /Pages /Kids [{kids}] /Count {len(self.pages)} >>".encode()
        out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
        offsets = []
        for i, body in enumerate(self.objects, start=1):
            offsets.append(len(out))
            out += f"{i} 0 obj\n".encode() + body + b"\nendobj\n"
        xref = len(out)
        out += f"xref\n0 {len(self.objects) + 1}\n0000000000 65535 f \n".encode()
        out += b"".join(f"{o:010d} 00000 n \n".encode() for o in offsets)
        out += (
            f"trailer\n<< /Size {len(self.objects) + 1} /Root 1 0 R >>\nstartxref\n{xref}\n%%EOF\n"
        ).encode()
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_bytes(bytes(out))
        tmp.replace(path)


class _Ops:
    """A page's content stream."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []

    def op(self, *items: float | str | bytes) -> None:
        words = [
            i if isinstance(i, bytes) else (i.encode() if isinstance(i, str) else _num(i).encode())
            for i in items
        ]
        self.parts.append(b" ".join(words))

    def text(self, x: float, y: float, size: float, s: str) -> None:
        self.op("BT /F1", size, "Tf", x, y, "Td", _text(s), "Tj ET")

    def line(self, x0: float, y0: float, x1: float, y1: float) -> None:
        self.op(x0, y0, "m", x1, y1, "l S")

    def data(self) -> bytes:
        return b"\n".join(self.parts) + b"\n"


def _scale_bar(ops: _Ops, x: float, y: float) -> None:
    """The 10 cm bar from (x, y): one 1 pt line exactly :data:`SCALE_BAR_PT` long (butt caps,
    so the ink is the length), end ticks, and its label."""
    ops.op("q 0 0 0 RG 1 w 0 J [] 0 d")
    ops.op("/ScaleBar BMC")
    ops.line(x, y, x + SCALE_BAR_PT, y)
    ops.op("EMC")
    ops.op(0.5, "w")
    for xt in (x, x + SCALE_BAR_PT / 2, x + SCALE_BAR_PT):
        ops.line(xt, y - 3, xt, y + 3)
    ops.op("Q")
    ops.text(x + SCALE_BAR_PT + 6, y - 3, 8, "10 cm: check it measures 10 cm (print at 100 %)")


def _mark_cross(ops: _Ops, x: float, y: float) -> None:
    """A registration cross and circle centred on (x, y), black over a white underlay."""
    r = 7.0
    for width, grey in ((2.2, 1), (0.6, 0)):
        ops.op(f"{grey} {grey} {grey} RG", width, "w")
        ops.line(x - r, y, x + r, y)
        ops.line(x, y - r, x, y + r)
        ops.op(x + r * 0.6, y, "m")
        for k in range(1, 17):
            a = 2 * math.pi * k / 16
            ops.op(x + r * 0.6 * math.cos(a), y + r * 0.6 * math.sin(a), "l")
        ops.op("S")


# --------------------------------------------------------------------------- the pages


def _pad_image(
    pad: PadDesign, size_pt: tuple[float, float], max_px: int
) -> tuple[np.ndarray, float]:
    """The pad's top view with at most ``max_px`` on its longer side and at most 100 dpi;
    returns (rgb, points per pixel)."""
    m_per_px = max(max(pad.size_m) / max_px, 0.0254 / 100)
    rgb = pad.top_view(m_per_px)
    # the image's pixels span the pad exactly: its own scale from its pixel count
    return rgb, size_pt[0] / rgb.shape[1]


def _tile_page(
    pdf: _Pdf, lay: Layout, pad: PadDesign, rgb: np.ndarray, row: int, col: int, page_no: int
) -> None:
    ph = lay.page_pt[1]
    cw, ch = lay.content_pt
    x0, y0 = lay.tile_origin_pt(row, col)
    sx = lay.pad_pt[0] / rgb.shape[1]
    sy = lay.pad_pt[1] / rgb.shape[0]
    c0, c1 = math.floor(x0 / sx), min(rgb.shape[1], math.ceil((x0 + cw) / sx))
    r0, r1 = math.floor(y0 / sy), min(rgb.shape[0], math.ceil((y0 + ch) / sy))
    ops = _Ops()
    images = {}
    if c1 > c0 and r1 > r0:
        img = pdf.image(rgb[r0:r1, c0:c1])
        images["Im1"] = img
        w, h = (c1 - c0) * sx, (r1 - r0) * sy
        left = MARGIN_PT + c0 * sx - x0
        top = ph - MARGIN_PT - (r0 * sy - y0)
        ops.op("q", MARGIN_PT, MARGIN_PT, cw, ch, "re W n")
        ops.op("q", w, 0, 0, h, left, top - h, "cm /Im1 Do Q")
        ops.op("Q")
    # the pad's part on this page: (x, y) ranges in pad points
    xa, xb = x0, min(x0 + cw, lay.pad_pt[0])
    ya, yb = y0, min(y0 + ch, lay.pad_pt[1])

    def page_x(px: float) -> float:
        return MARGIN_PT + px - x0

    def page_y(py: float) -> float:
        return ph - MARGIN_PT - (py - y0)

    # its outline (thin grey): where the pad ends on this page
    ops.op("q 0.6 0.6 0.6 RG 0.3 w", page_x(xa), page_y(yb), xb - xa, yb - ya, "re S Q")
    ops.op("q")
    # shared strips: their middle lines (dashed, white underlay) and crosses on them at pad
    # points both pages sharing the strip hold
    sxs, sys_ = lay.step_pt
    xs = [c * sxs + OVERLAP_PT / 2 for c in (col, col + 1) if 0 < c < lay.cols]
    ys = [r * sys_ + OVERLAP_PT / 2 for r in (row, row + 1) if 0 < r < lay.rows]
    for style in ("1 1 1 RG 1.4 w [] 0 d", "0 0 0 RG 0.6 w [4 3] 0 d"):
        ops.op(style)
        for px in xs:
            ops.line(page_x(px), page_y(ya), page_x(px), page_y(yb))
        for py in ys:
            ops.line(page_x(xa), page_y(py), page_x(xb), page_y(py))
    ops.op("[] 0 d")
    points = [(px, y0 + ch * k / 4) for px in xs for k in (1, 2, 3)]
    points += [(x0 + cw * k / 4, py) for py in ys for k in (1, 2, 3)]
    points += [(px, py) for px in xs for py in ys]
    for px, py in points:
        if px <= xb and py <= yb:
            _mark_cross(ops, page_x(px), page_y(py))
    ops.op("Q")
    w_m, h_m = pad.size_m
    ops.text(
        MARGIN_PT,
        ph - MARGIN_PT + 8,
        8,
        f"{pad.name} {w_m:g} x {h_m:g} m - page {page_no} of {lay.pages}: tile row {row + 1} of "
        f"{lay.rows}, column {col + 1} of {lay.cols}. Cut along a dashed line, match the crosses.",
    )
    _scale_bar(ops, MARGIN_PT, MARGIN_PT / 2)
    pdf.page(lay.page_pt, ops.data(), images)


def _map_page(pdf: _Pdf, lay: Layout, pad: PadDesign, thumb: np.ndarray, dpi: float) -> None:
    pw, ph = lay.page_pt
    ops = _Ops()
    w_m, h_m = pad.size_m
    orient = "landscape" if lay.landscape else "portrait"
    title = 16 if pw > 700 else 13
    lines = [
        (title, f"Landing pad {pad.name}: {w_m:g} m x {h_m:g} m at true scale"),
        (
            9,
            f"{lay.pages} pages of {PAPER_NAMES[lay.paper]} {orient}: "
            f"this map, then {lay.tiles} tiles ({lay.rows} rows x {lay.cols} columns) from the "
            "pad's north-west corner.",
        ),
        (9, "Print at 100 % (actual size, no 'fit to page'); check the scale bar measures 10 cm."),
        (
            9,
            f"Neighbouring tiles share a {OVERLAP_PT / PT_PER_M * 1000:.0f} mm strip: cut one page "
            "along its dashed line, lay it on the",
        ),
        (9, "next so the crosses' halves meet, tape it from the back. Top of each page = north."),
        (9, f"Pad image {dpi:.0f} dpi. Print matte; no gloss or laminate (glare hides the pad)."),
    ]
    y = ph - 40
    for size, s in lines:
        ops.text(36, y, size, s)
        y -= size + 6
    # the whole pad with the tile grid, as large as fits below the text
    box_w, box_h = pw - 72, y - 90
    scale = min(box_w / lay.pad_pt[0], box_h / lay.pad_pt[1])
    mw, mh = lay.pad_pt[0] * scale, lay.pad_pt[1] * scale
    left, top = 36 + (box_w - mw) / 2, y - 10
    images = {"Im1": pdf.image(thumb)}
    ops.op("q", mw, 0, 0, mh, left, top - mh, "cm /Im1 Do Q")
    cw, ch = lay.content_pt
    font = max(5.0, min(14.0, 0.3 * min(cw, ch) * scale))
    ops.op("q 0.85 0 0 RG 0.6 w")
    for r in range(lay.rows):
        for c in range(lay.cols):
            x0, y0 = lay.tile_origin_pt(r, c)
            tw = min(cw, lay.pad_pt[0] - x0) * scale
            th = min(ch, lay.pad_pt[1] - y0) * scale
            tx, ty = left + x0 * scale, top - y0 * scale
            ops.op(tx, ty - th, tw, th, "re S")
            label = str(2 + r * lay.cols + c)
            size = min(font, 0.9 * min(tw / (0.56 * len(label)), th))
            lx, ly = tx + tw / 2 - 0.28 * size * len(label), ty - th / 2 - size / 3
            ops.op("1 1 1 rg", lx - 1, ly - 0.25 * size, 0.56 * size * len(label) + 2, size, "re f")
            ops.op("0 0 0 rg")
            ops.text(lx, ly, size, label)
    ops.op("Q")
    ops.text(36, 62, 9, f"Tile grid: page numbers on the pad, north up ({lay.pages} pages).")
    _scale_bar(ops, 36, 40)
    pdf.page(lay.page_pt, ops.data(), images)


def write_pdf(pad: PadDesign, out: str | Path, paper: str = "a4") -> PrintReport:
    """The pad at true scale on ``paper`` pages: the assembly map, then the tiles."""
    out = Path(out)
    lay = layout(pad.size_m, paper)
    rgb, pt_per_px = _pad_image(pad, lay.pad_pt, PDF_MAX_PX)
    thumb_px = max(pad.size_m) / 600
    thumb = pad.top_view(thumb_px)
    pdf = _Pdf()
    pdf.add(b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding >>")
    dpi = 72.0 / pt_per_px
    _map_page(pdf, lay, pad, thumb, dpi)
    for r in range(lay.rows):
        for c in range(lay.cols):
            _tile_page(pdf, lay, pad, rgb, r, c, 2 + r * lay.cols + c)
    out.parent.mkdir(parents=True, exist_ok=True)
    pdf.write(out)
    return PrintReport(out, lay.pages, lay.rows, lay.cols, paper, lay.landscape, dpi)


def write_png(pad: PadDesign, out: str | Path, dpi: float) -> PrintReport:
    """The whole pad as one PNG at ``dpi`` (its physical size in the file's pHYs, for a print
    shop).

    Raises:
        ConfigError: a dpi that is not positive, or an image over :data:`PNG_MAX_PX` a side.
    """
    from PIL import Image

    if not (math.isfinite(dpi) and dpi > 0):
        raise ConfigError(f"--dpi: expected a positive number, got {dpi}")
    side_px = max(pad.size_m) / 0.0254 * dpi
    if side_px > PNG_MAX_PX:
        most = PNG_MAX_PX * 0.0254 / max(pad.size_m)
        raise ConfigError(
            f"--dpi {dpi:g}: a {max(pad.size_m):g} m pad would be {side_px:.0f} px a side, at most "
            f"{PNG_MAX_PX}; use --dpi {math.floor(most)} or less"
        )
    out = Path(out)
    rgb = pad.top_view(0.0254 / dpi)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(rgb, "RGB").save(out, dpi=(dpi, dpi))
    return PrintReport(out, 1, 1, 1, "png", False, dpi)
