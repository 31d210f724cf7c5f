"""The Python package needle_sim (src/needle_sim) as catkin builds it: catkin_python_setup()
in CMakeLists.txt reads this file; the devel space relays to src/needle_sim and `make
install` puts the package in <prefix>/lib/python3/dist-packages, beside the needle_sim.msg,
.srv and .cfg that catkin generates. pip reads pyproject.toml, which takes the version from
here (package.xml's, through catkin_pkg). README.md, "The Python package"."""
from setuptools import find_packages, setup

try:
    from catkin_pkg.python_setup import generate_distutils_setup
except ImportError:  # pip outside a ROS environment: package.xml read here
    import xml.etree.ElementTree as ElementTree

    def generate_distutils_setup(**kwargs):
        return dict(kwargs, version=ElementTree.parse("package.xml").getroot().findtext("version"))

info = generate_distutils_setup(packages=find_packages("src", include=["needle_sim", "needle_sim.*"]),
                                package_dir={"": "src"})
# pyproject.toml's [project] holds the rest of the metadata (name, description, licence,
# dependencies); setuptools takes no field from both.
setup(**{k: info[k] for k in ("version", "packages", "package_dir")})
