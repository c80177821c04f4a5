"""xmetro_ros: per-point error prediction for laser line scanners, over ROS 2.

Pure computation (geometry, simulator, features, models, closed loop) lives in ROS-free modules; the node and the
bag tools wire them to ROS 2 topics and MCAP files. Units inside: millimetres, milliseconds; on ROS topics: SI.
"""

from importlib import metadata as _metadata


def _version() -> str:
    """The installed distribution's version (set from package.xml at build time); from package.xml in a plain
    source tree that was never installed."""
    try:
        return _metadata.version("xmetro_ros")
    except _metadata.PackageNotFoundError:
        import re
        from pathlib import Path

        xml = Path(__file__).resolve().parent.parent / "package.xml"
        m = re.search(r"<version>\s*([^<\s]+)\s*</version>", xml.read_text()) if xml.exists() else None
        return m.group(1) if m else "0+unknown"


__version__ = _version()
