"""Test campaigns (METHOD.md §7, the paper's Tables 3–6 and Figs. 7–9): ``stats`` (pure
statistics), ``campaign`` (discovery, wear table, parallel analysis), ``worker`` (per-log work),
``tables`` (the tables, pure), ``figures`` (PNG), ``render`` (CSV, Markdown, HTML), ``pipeline``
(``build_report``)."""
