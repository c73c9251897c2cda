import sys

from jaximu.cli import main

sys.exit(main())
