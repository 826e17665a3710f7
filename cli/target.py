"""``heartcv target``: write a calibration target file and its printable PNG and PDF."""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import click

from .options import BadInput, Float, IntPair, announce, emit_json, guard_outputs, json_opt

log = logging.getLogger(__name__)

def _max_squares():
    from heartcv.targets import MAX_SQUARES

    return MAX_SQUARES


# COLSxROWS -> (cols, rows), each in 3 .. MAX_SQUARES (a target file's fewer than 3: TargetSpec refuses them)
GridSize = functools.partial(IntPair, "COLSxROWS", "11x8", _max_squares, low=3)


@click.command()
@click.option("--type", "kind", type=click.Choice(("charuco", "chessboard")), required=True,
              help="ChArUco board (partial views allowed) or plain chessboard.")
@click.option("--squares", type=GridSize(), default=None, metavar="COLSxROWS",
              help="ChArUco: squares across x down (e.g. 11x8).")
@click.option("--inner-corners", type=GridSize(), default=None, metavar="COLSxROWS",
              help="Chessboard: inner corners across x down (OpenCV's pattern size, e.g. 9x6).")
@click.option("--square-mm", type=Float(0, 1000, lo_open=True, hi_open=True), required=True,
              help="Square side in mm.")
@click.option("--marker-mm", type=Float(0, 1000, lo_open=True, hi_open=True), default=None,
              help="ChArUco: marker side in mm (smaller than the square).")
@click.option("--dict", "dictionary", default="DICT_5X5_250", show_default=True,
              help="ChArUco: ArUco dictionary (OpenCV name, e.g. DICT_5X5_250, DICT_6X6_250).")
@click.option("--legacy", is_flag=True,
              help="ChArUco: OpenCV's legacy pattern (boards made before OpenCV 4.6 with an even number of rows).")
@click.option("--inverted", is_flag=True,
              help="ChArUco: colours swapped, white markers on black squares (caliscope's boards); detection then "
                   "looks for the markers in the negative image.")
@click.option("--dpi", type=Float(0, 10000, lo_open=True), default=300.0, show_default=True,
              help="Requested print resolution; adjusted so that every square is a whole number of pixels.")
@click.option("--margin-mm", type=Float(0, 1000, hi_open=True), default=None,
              help="White margin around the squares in mm (default: one square).")
@click.option("--name", default=None, help="Target name (default: the output file's stem).")
@click.option("-o", "--output", type=click.Path(dir_okay=False), required=True,
              help="Target file (.yaml); the PNG and PDF are written beside it with the same stem.")
@json_opt
def target(kind, squares, inner_corners, square_mm, marker_mm, dictionary, legacy, inverted, dpi, margin_mm, name,
           output, as_json):
    """Write a calibration target: OUTPUT (.yaml) plus OUTPUT's stem .png and .pdf to print.

    The image has an exact physical size: the DPI is adjusted slightly so that each square is a whole number
    of pixels (e.g. 12 mm squares at 300 dpi: 298.45 dpi, 141 px). Print the PDF at 100 % (actual size).
    """
    from heartcv.io import write_board_image, write_target
    from heartcv.targets import INCH_M, render_board

    out = Path(output)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise BadInput(f"-o/--output: a .yaml file expected, got {output}")
    png, pdf = out.with_suffix(".png"), out.with_suffix(".pdf")
    _refuse_sibling_target(out, png, pdf)
    guard_outputs({}, {}, files=[("-o/--output", out, ("heartcv.target",)), ("-o/--output (PNG)", png, ("png",)),
                                 ("-o/--output (PDF)", pdf, ("pdf",))])
    grid = _grid(kind, squares, inner_corners, marker_mm, legacy or inverted)
    spec = _spec(kind, grid, square_mm, marker_mm, dictionary, legacy, name or out.stem, inverted)
    margin_m = spec.square_m if margin_mm is None else margin_mm / 1000
    image, px_per_m = render_board(spec, dpi=dpi, margin_m=margin_m)
    h, w = image.shape
    size_m = (w / px_per_m, h / px_per_m)
    write_board_image(png, pdf, image, px_per_m * INCH_M, size_m)
    write_target(out, spec, png=png, pdf=pdf, px_per_m=px_per_m, image_size=(w, h))  # last: marks completion

    cols, rows = spec.squares_count
    summary = {
        "name": spec.name, "type": spec.type, "output": output, "png": str(png), "pdf": str(pdf),
        "squares": list(spec.squares_count), "inner_corners": list(spec.inner_size), "corners": spec.n_corners,
        "square_mm": spec.square_m * 1e3, "marker_mm": None if spec.marker_m is None else spec.marker_m * 1e3,
        "dictionary": spec.dictionary, "legacy_pattern": spec.legacy, "inverted": spec.inverted,
        "board_size_mm": [v * 1e3 for v in spec.board_size_m], "page_size_mm": [v * 1e3 for v in size_m],
        "margin_mm": (w - cols * round(spec.square_m * px_per_m)) / 2 / px_per_m * 1e3,
        "dpi": px_per_m * INCH_M, "dpi_requested": dpi, "px_per_m": px_per_m,
        "square_px": int(round(spec.square_m * px_per_m)), "image_size_px": [w, h],
    }
    if as_json:
        emit_json(summary)
    else:
        bw, bh = summary["board_size_mm"]
        announce(log, "wrote %s (+ %s, %s): %s %dx%d squares, %.1f x %.1f mm at %.6g dpi (%d px per %g mm square); "
                 "print the PDF at 100 %%", output, png.name, pdf.name, spec.type, cols, rows, bw, bh,
                 summary["dpi"], summary["square_px"], spec.square_m * 1e3)


def _refuse_sibling_target(out: Path, png: Path, pdf: Path) -> None:
    """Exit 2 when another target file of the same stem (``a.yml`` beside ``a.yaml``) owns the PNG and PDF this
    run would write: replacing them would leave that target describing one board and its printable files another
    (a person printing ``a.pdf`` for ``a.yaml`` would get the wrong board)."""
    import os

    from heartcv.tracker.files import heartcv_format

    try:
        siblings = [p for p in out.parent.iterdir() if p.stem == out.stem and p.suffix.lower() in (".yaml", ".yml")]
    except OSError:
        return
    for other in siblings:
        if other.name == out.name or (out.exists() and os.path.samefile(other, out)):
            continue
        if heartcv_format(other) == "heartcv.target" and (png.exists() or pdf.exists()):
            raise BadInput(f"-o/--output: {out}: its {png.name} and {pdf.name} belong to the target {other}, which "
                           "would then describe another board than its printable files; give this target another "
                           "name, or remove that target first")


def _grid(kind, squares, inner_corners, marker_mm, charuco_flag):

    """The board's grid from the options of its type; exit 2 for a missing or conflicting option."""
    if kind == "charuco":
        if inner_corners is not None:
            raise BadInput("--inner-corners applies to chessboards; a ChArUco board is given by --squares")
        if squares is None:
            raise BadInput("--squares is required for --type charuco (e.g. --squares 11x8)")
        if marker_mm is None:
            raise BadInput("--marker-mm is required for --type charuco")
        return squares
    if squares is not None:
        raise BadInput("--squares applies to ChArUco boards; a chessboard is given by --inner-corners")
    if inner_corners is None:
        raise BadInput("--inner-corners is required for --type chessboard (e.g. --inner-corners 9x6)")
    if marker_mm is not None or charuco_flag:
        raise BadInput("--marker-mm, --legacy and --inverted apply to ChArUco boards only")
    return inner_corners


def _spec(kind, grid, square_mm, marker_mm, dictionary, legacy, name, inverted=False):
    """The target the options describe. TargetSpec refuses a marker not smaller than the square, an unknown
    dictionary or one with too few markers, fewer than 3 squares a way (InputError naming the field: exit 2)."""
    from heartcv.targets import TargetSpec

    charuco = kind == "charuco"
    return TargetSpec(kind, grid, square_mm / 1000, marker_mm / 1000 if charuco else None,
                      dictionary.upper() if charuco else None, legacy, name, inverted)
