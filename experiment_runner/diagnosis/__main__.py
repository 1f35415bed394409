"""``python -m experiment_runner.diagnosis diagnose|synth ...`` (until wired into ``nanostage``)."""
import sys

from .cli import main

sys.exit(main())
