import sys

from services.localizer.node import main

sys.exit(main())
