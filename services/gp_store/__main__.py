import sys

from services.gp_store.node import main

sys.exit(main())
