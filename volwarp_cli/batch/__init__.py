"""``volwarp batch``: a manifest of scans through a chain of volwarp steps.

manifest (load and check the manifest, find the scans, shard them), plan (each
scan's concrete commands; Make's up-to-date rule), run (the local pool of
subprocesses, stops, retries), report (progress lines, the summary line, the
JSON run report).
"""
