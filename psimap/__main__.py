import sys

from psimap.cli import main

sys.exit(main())
