"""Analysis of sweep results: reads result files only (no SUMO, no torch).

- ``analysis.results``: ``load_results``, ``summarise`` (mean and 95 % t-CI), ``to_parquet``
- ``analysis.tables``: paper-shaped macro/micro tables with safety counts, per-cell table
- ``analysis.figures``: seaborn figures with CIs (penetration, density, micro, weather)
- ``analysis.findings``: short data-driven findings
- ``analysis.report``: ``build_report`` (PDF with reportlab)
"""
