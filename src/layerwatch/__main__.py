import sys

from layerwatch.cli import main

sys.exit(main())
