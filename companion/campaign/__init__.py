"""``companion campaign``: matrices of lockstep flights (controllers x scenarios x seeds) on a
distributed engine (Dask), scored from each flight's ``report.json``.

``scenarios`` (the library and the sampled starts), ``runner`` (one flight in its own folder),
``engine`` (Dask, resumable, progress bar), ``summary`` (table, Markdown, plots). The engine is
the optional extra ``.[campaign]``; nothing here runs on the vehicle.
"""
