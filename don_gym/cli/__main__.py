import sys

from don_gym.cli import main

sys.exit(main())
