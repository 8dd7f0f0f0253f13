"""`python -m bench.hostile [--area AREA ...] [--list]`: run every probe module's probes (see runner)."""
import sys

from bench.hostile.runner import main

sys.exit(main())
