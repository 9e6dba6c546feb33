import os
from glob import glob

from setuptools import find_packages, setup

package_name = "object_query"
# The bundled sample map lives at the repository root (data/); install it into this package's
# share directory so the server finds it from any working directory.
_data = [p for p in glob(os.path.join("..", "..", "data", "*")) if os.path.isfile(p)]

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/data", _data),
        ("share/" + package_name + "/config", glob(os.path.join("config", "*.yaml"))),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="Home Robot maintainers",
    maintainer_email="maintainers@home-robot.dev",
    description="Semantic object database over a Gaussian-splatting map.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "object_query_server = object_query.object_query_server:main",
            "object_query_client = object_query.object_query_client:main",
        ],
    },
)
