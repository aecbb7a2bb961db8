"""What a run produces, in one place: MCAP output channels (:mod:`.channels`), the log
channel's lines (:mod:`.log`), figures (:mod:`.figures`), the summary document
(:mod:`.summary`, one builder for every command), the Markdown and HTML reports
(:mod:`.markdown`, :mod:`.html`) and the Foxglove layout (:mod:`.layout`).

Everything here renders results the stages computed; nothing here computes them.
"""

from pipeline.products.summary import build_summary, flight_summary, jsonable

__all__ = ["build_summary", "flight_summary", "jsonable"]
