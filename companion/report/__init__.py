"""Flight reports from a log: figures (``report.json``), plots and the HTML page."""
