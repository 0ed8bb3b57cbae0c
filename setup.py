"""Package list for setuptools; everything else is declared in pyproject.toml.

``pyproject.toml`` alone cannot combine ``packages.find`` with packages mapped from other folders,
so the list is built here: every package under protocol/, mapper/, clients/ and govnesf/, plus the
repository's ``checkpoints/`` and ``launch/`` folders mapped into the wheel as the data packages
``govnesf.checkpoints`` and ``govnesf.launch`` (found at run time by ``govnesf.resources``).
"""

from setuptools import find_packages, setup

DATA_PACKAGES = {"govnesf.checkpoints": "checkpoints", "govnesf.launch": "launch"}

setup(
    packages=[
        *find_packages(include=["protocol", "protocol.*", "mapper", "mapper.*", "clients", "clients.*",
                                "govnesf", "govnesf.*"]),
        *DATA_PACKAGES,
    ],
    package_dir=DATA_PACKAGES,
)
