"""Measurement harnesses behind the scripts that write the project's reports
(``scripts/stability_margin.py`` → ``docs/stability.md``); tests reach the same code."""
