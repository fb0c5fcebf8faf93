"""The self-contained HTML layer viewer (``page.py`` + ``viewer.html``)."""

from .page import MaskLayers, build_view_html, raster_masks, read_view_data, write_view

__all__ = ["MaskLayers", "build_view_html", "raster_masks", "read_view_data", "write_view"]
