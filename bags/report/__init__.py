"""Reports of a replay: pictures of frames (prediction vs ground truth), the reliability diagram,
and the self-contained ``report.html`` (inline CSS and SVG charts, nothing fetched).

Public names: :func:`comparison_picture`, :func:`encode_png`, :func:`encode_gif`,
:func:`reliability_picture` and :func:`render_report`. Modules: :mod:`~bags.report.pictures`,
:mod:`~bags.report.reliability`, :mod:`~bags.report.html` and :mod:`~bags.report.svg_plots`.
"""

from .html import render_report
from .pictures import comparison_picture, encode_gif, encode_png
from .reliability import reliability_picture

__all__ = ["comparison_picture", "encode_gif", "encode_png", "reliability_picture", "render_report"]
