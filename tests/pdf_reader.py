"""A reader for the PDF subset ``visland pad print`` writes (no PDF library is installed): the
file's structure checked (header, xref offsets, trailer, page tree), each page's MediaBox, its
content stream interpreted (q/Q, cm, colours, lines, rectangles, clipping, images, text,
marked content), and the page rasterised with Pillow to look at.

It reads the bytes of the file, not the writer's data: a page count, a MediaBox or a scale bar
asserted from here is what a PDF viewer would find.
"""

from __future__ import annotations

import itertools
import re
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

_TOKEN = re.compile(
    rb"\s*(?:(?P<num>[+-]?(?:\d+\.?\d*|\.\d+))(?![\w.])|(?P<name>/[^\s/\[\]()<>]+)"
    rb"|(?P<str>\((?:\\.|[^\\)])*\))|(?P<open>\[)|(?P<close>\])|(?P<op>[A-Za-z*'\"]+))",
    re.S,
)


@dataclass
class Page:
    media_box: tuple[float, float, float, float]
    content: bytes
    xobjects: dict[str, int]
    images: list[dict] = field(default_factory=list)
    """Each drawn image: name, width/height in pixels, (x, y, w, h) in points, its RGB."""
    scale_bars: list[tuple[float, float, float, float]] = field(default_factory=list)
    """Line segments drawn inside ``/ScaleBar BMC ... EMC`` (points, after the CTM)."""
    texts: list[str] = field(default_factory=list)
    ops: list[tuple[str, list]] = field(default_factory=list)


class PdfFile:
    def __init__(self, path: str | Path) -> None:
        self.data = Path(path).read_bytes()
        assert self.data.startswith(b"%PDF-1."), "no PDF header"
        assert self.data.rstrip().endswith(b"%%EOF"), "no %%EOF"
        start = int(re.search(rb"startxref\s+(\d+)\s+%%EOF\s*$", self.data).group(1))
        assert self.data[start:].startswith(b"xref"), "startxref does not point at the xref"
        head = re.match(rb"xref\s+0\s+(\d+)\s+", self.data[start:])
        count = int(head.group(1))
        table = self.data[start + head.end() :].split(b"\n")[:count]
        self.offsets = {}
        for num, row in enumerate(table):
            off, _, kind = row.split()[:3]
            if kind == b"n":
                self.offsets[num] = int(off)
                assert self.data[int(off) :].startswith(f"{num} 0 obj".encode()), (
                    f"xref offset of object {num} is wrong"
                )
        trailer = self.data[self.data.rindex(b"trailer") :]
        root = int(re.search(rb"/Root\s+(\d+)\s+0\s+R", trailer).group(1))
        pages_ref = int(re.search(rb"/Pages\s+(\d+)\s+0\s+R", self.dict_of(root)).group(1))
        tree = self.dict_of(pages_ref)
        kids = [
            int(k)
            for k in re.findall(rb"(\d+)\s+0\s+R", re.search(rb"/Kids\s*\[(.*?)\]", tree).group(1))
        ]
        assert int(re.search(rb"/Count\s+(\d+)", tree).group(1)) == len(kids)
        self.pages = [self._page(k) for k in kids]

    def _body(self, num: int) -> bytes:
        off = self.offsets[num]
        start = self.data.index(b"obj", off) + 3
        return self.data[start : self.data.index(b"endobj", start)]

    def dict_of(self, num: int) -> bytes:
        body = self._body(num)
        return body.split(b"stream")[0] if b"stream" in body else body

    def stream_of(self, num: int) -> bytes:
        body = self._body(num)
        head = body[: body.index(b"stream")]
        length = int(re.search(rb"/Length\s+(\d+)", head).group(1))
        start = body.index(b"stream") + len(b"stream\n")
        data = body[start : start + length]
        assert body[start + length :].strip() == b"endstream", f"object {num}: bad /Length"
        return zlib.decompress(data) if b"/FlateDecode" in head else data

    def _page(self, num: int) -> Page:
        d = self.dict_of(num)
        box = tuple(float(v) for v in re.search(rb"/MediaBox\s*\[([^\]]*)\]", d).group(1).split())
        contents = int(re.search(rb"/Contents\s+(\d+)\s+0\s+R", d).group(1))
        xo = re.search(rb"/XObject\s*<<(.*?)>>", d)
        xobjects = {}
        if xo:
            for name, ref in re.findall(rb"/(\w+)\s+(\d+)\s+0\s+R", xo.group(1)):
                xobjects[name.decode()] = int(ref)
        page = Page(box, self.stream_of(contents), xobjects)
        self._interpret(page)
        return page

    def image(self, num: int) -> np.ndarray:
        head = self.dict_of(num)
        w = int(re.search(rb"/Width\s+(\d+)", head).group(1))
        h = int(re.search(rb"/Height\s+(\d+)", head).group(1))
        assert b"/DeviceRGB" in head and b"/BitsPerComponent 8" in head
        return np.frombuffer(self.stream_of(num), np.uint8).reshape(h, w, 3)

    def _interpret(self, page: Page) -> None:
        stack: list = []
        ctm = np.eye(3)
        saved: list[np.ndarray] = []
        marked: list[str] = []
        path_start = None
        array: list | None = None
        for m in _TOKEN.finditer(page.content):
            if m.group("num") is not None:
                (array if array is not None else stack).append(float(m.group("num")))
            elif m.group("name") is not None:
                (array if array is not None else stack).append(m.group("name")[1:].decode())
            elif m.group("str") is not None:
                raw = m.group("str")[1:-1]
                stack.append(re.sub(rb"\\(.)", rb"\1", raw).decode("latin-1"))
            elif m.group("open"):
                array = []
            elif m.group("close"):
                stack.append(array)
                array = None
            else:
                op = m.group("op").decode()
                page.ops.append((op, list(stack)))
                if op == "q":
                    saved.append(ctm.copy())
                elif op == "Q":
                    ctm = saved.pop()
                elif op == "cm":
                    a, b, c, d, e, f = stack[-6:]
                    ctm = np.array([[a, b, 0], [c, d, 0], [e, f, 1]]) @ ctm
                elif op == "BMC":
                    marked.append(stack[-1])
                elif op == "EMC":
                    marked.pop()
                elif op == "m":
                    path_start = self._xy(ctm, *stack[-2:])
                elif op == "l":
                    end = self._xy(ctm, *stack[-2:])
                    if "ScaleBar" in marked:
                        page.scale_bars.append((*path_start, *end))
                    path_start = end
                elif op == "Tj":
                    page.texts.append(stack[-1])
                elif op == "Do":
                    x0, y0 = self._xy(ctm, 0, 0)
                    x1, y1 = self._xy(ctm, 1, 1)
                    rgb = self.image(page.xobjects[stack[-1]])
                    page.images.append(
                        {
                            "name": stack[-1],
                            "width_px": rgb.shape[1],
                            "height_px": rgb.shape[0],
                            "rect_pt": (x0, y0, x1 - x0, y1 - y0),
                            "rgb": rgb,
                        }
                    )
                stack.clear()

    @staticmethod
    def _xy(ctm: np.ndarray, x: float, y: float) -> tuple[float, float]:
        v = np.array([x, y, 1.0]) @ ctm
        return float(v[0]), float(v[1])


def render(page: Page, px_per_pt: float = 1.0):
    """The page as a Pillow image (white paper): images (clipped to the current ``re W n``),
    strokes, filled rectangles and text. Dashes are drawn as dashes; curves as polylines."""
    from PIL import Image, ImageDraw

    w, h = page.media_box[2], page.media_box[3]
    img = Image.new("RGB", (round(w * px_per_pt), round(h * px_per_pt)), "white")
    draw = ImageDraw.Draw(img)

    def dev(x: float, y: float) -> tuple[float, float]:
        return x * px_per_pt, (h - y) * px_per_pt

    state = {
        "ctm": np.eye(3),
        "stroke": (0, 0, 0),
        "fill": (0, 0, 0),
        "w": 1.0,
        "dash": [],
        "clip": None,
    }
    saved = []
    path: list[list[tuple[float, float]]] = []
    rects: list[tuple[float, float, float, float]] = []
    text_at = (0.0, 0.0)
    font_size = 10.0
    xy = PdfFile._xy
    for op, args in page.ops:
        if op == "q":
            saved.append(dict(state))
        elif op == "Q":
            state = saved.pop()
        elif op == "cm":
            a, b, c, d, e, f = args[-6:]
            state["ctm"] = np.array([[a, b, 0], [c, d, 0], [e, f, 1]]) @ state["ctm"]
        elif op in ("RG", "rg"):
            col = tuple(round(255 * v) for v in args[-3:])
            state["stroke" if op == "RG" else "fill"] = col
        elif op == "w":
            state["w"] = args[-1]
        elif op == "d":
            state["dash"] = args[-2]
        elif op == "m":
            path.append([xy(state["ctm"], *args[-2:])])
        elif op == "l":
            path[-1].append(xy(state["ctm"], *args[-2:]))
        elif op == "re":
            x, y, rw, rh = args[-4:]
            rects.append((*xy(state["ctm"], x, y), rw, rh))
        elif op in ("S", "f"):
            width = max(1, round(state["w"] * px_per_pt))
            for x, y, rw, rh in rects:
                box = [dev(x, y + rh), dev(x + rw, y)]
                if op == "f":
                    draw.rectangle(box, fill=state["fill"])
                else:
                    draw.rectangle(box, outline=state["stroke"], width=width)
            for poly in path:
                pts = [dev(*p) for p in poly]
                if state["dash"]:
                    _dashed(
                        draw, pts, [v * px_per_pt for v in state["dash"]], state["stroke"], width
                    )
                else:
                    draw.line(pts, fill=state["stroke"], width=width)
            path, rects = [], []
        elif op == "n":  # after W: the clip is the rectangle
            if rects:
                x, y, rw, rh = rects[-1]
                state["clip"] = (x, y, rw, rh)
            path, rects = [], []
        elif op == "Do":
            x0, y0 = xy(state["ctm"], 0, 0)
            x1, y1 = xy(state["ctm"], 1, 1)
            rgb = next(i["rgb"] for i in page.images if i["name"] == args[-1])
            box = [dev(x0, y1), dev(x1, y0)]
            bw, bh = round(box[1][0] - box[0][0]), round(box[1][1] - box[0][1])
            if bw > 0 and bh > 0:
                tile = Image.fromarray(rgb).resize((bw, bh), Image.Resampling.NEAREST)
                layer = Image.new("RGB", img.size, "white")
                mask = Image.new("L", img.size, 0)
                layer.paste(tile, (round(box[0][0]), round(box[0][1])))
                ImageDraw.Draw(mask).rectangle(
                    [
                        round(box[0][0]),
                        round(box[0][1]),
                        round(box[0][0]) + bw - 1,
                        round(box[0][1]) + bh - 1,
                    ],
                    fill=255,
                )
                if state["clip"] is not None:
                    cx, cy, cw, ch = state["clip"]
                    clip = Image.new("L", img.size, 0)
                    ImageDraw.Draw(clip).rectangle([dev(cx, cy + ch), dev(cx + cw, cy)], fill=255)
                    mask = Image.fromarray(np.minimum(np.asarray(mask), np.asarray(clip)))
                img.paste(layer, (0, 0), mask)
        elif op == "Tf":
            font_size = args[-1]
        elif op == "Td":
            text_at = xy(state["ctm"], *args[-2:])
        elif op == "Tj":
            x, y = dev(*text_at)
            draw.text(
                (x, y - font_size * px_per_pt * 0.8),
                args[-1],
                fill=state["fill"],
                font_size=max(6, font_size * px_per_pt),
            )
    return img


def _dashed(draw, pts, dash, colour, width) -> None:
    on, off = (dash + dash)[:2] if dash else (1, 0)
    for (x0, y0), (x1, y1) in itertools.pairwise(pts):
        length = float(np.hypot(x1 - x0, y1 - y0))
        t = 0.0
        while t < length:
            t1 = min(length, t + on)
            a, b = t / length, t1 / length
            draw.line(
                [
                    (x0 + a * (x1 - x0), y0 + a * (y1 - y0)),
                    (x0 + b * (x1 - x0), y0 + b * (y1 - y0)),
                ],
                fill=colour,
                width=width,
            )
            t = t1 + off
