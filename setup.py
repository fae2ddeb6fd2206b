"""Package discovery for the layout ``schemas/``, ``client/``, ``service/`` -> ``gcdtrav.schemas``, ...

pyproject.toml holds everything declarative. Only the package list lives here: setuptools' ``find`` has no
way to add the ``gcdtrav.`` prefix to folders found at the root, and a hand-written list once left
``gcdtrav.service.grid`` out of the wheel. Every folder with an ``__init__.py`` below the three roots is
a package.
"""

from setuptools import find_packages, setup

ROOTS = ("schemas", "client", "service")

setup(
    packages=[f"gcdtrav.{name}" for name in find_packages(include=[f"{root}*" for root in ROOTS])],
    package_dir={f"gcdtrav.{root}": root for root in ROOTS},
)
