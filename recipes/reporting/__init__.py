"""The results pages, generated from the files under ``results/``.

``load`` reads results files into records, ``tables`` turns records into markdown,
``figures`` draws the curves, ``pages`` puts the blocks of ``pages.yaml`` into the pages and
checks them; ``paper.yaml`` holds the paper's figures. ``recipes/report.py`` is the command.
"""
