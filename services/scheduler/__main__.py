import sys

from services.scheduler.node import main

sys.exit(main())
