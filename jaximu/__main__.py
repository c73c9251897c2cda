import sys

from jaximu.app import main

sys.exit(main())
