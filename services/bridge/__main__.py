import sys

from services.bridge.node import main

sys.exit(main())
