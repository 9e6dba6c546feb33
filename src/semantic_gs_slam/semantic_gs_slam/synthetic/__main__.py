"""``python -m semantic_gs_slam.synthetic``: write the synthetic home's frames (:func:`.scenes.main`)."""

import sys

from semantic_gs_slam.synthetic.scenes import main

if __name__ == "__main__":
    sys.argv[0] = "python -m semantic_gs_slam.synthetic"  # the usage line names the command, not __main__.py
    main()
