"""``python -m xmetro_ros.parts_seen OUT``: the documented command of the parts-seen study (docs/parts.md), kept at
its published path; the study is :mod:`xmetro_ros.parts.seen`."""

from .parts.seen import main

if __name__ == "__main__":
    main()
