"""python -m softrtc.conformance run|generate ... ([CF-19])."""

import sys

from .cli import main

sys.exit(main())
