"""``python -m rgbdslam ...``: the same command line as the ``rgbdslam`` script."""

from rgbdslam._entry import main

if __name__ == "__main__":
    main()
