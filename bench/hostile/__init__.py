"""The hostile bench: probes of the command line, bags, TF, signals, disks, node parameters and the arm.

Each probe states what it does to the software and what must happen (`Probe.expect`); `Probe.check`
runs it in a scratch folder and returns None when the expectation held, else one line saying what
happened instead. Probe modules in this package (one per area) expose `probes() -> list[Probe]`;
`python -m bench.hostile` runs every module's probes and writes bench/results/hostile.md + .json, and
`touchroller report` counts held / total.
"""

from bench.hostile.runner import load, run, to_markdown  # noqa: E402,F401 - the report's section interface
