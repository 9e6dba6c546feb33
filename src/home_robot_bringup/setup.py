from glob import glob

from setuptools import find_packages, setup

package_name = "home_robot_bringup"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/config/params", glob("config/params/*.yaml")),
        ("share/" + package_name + "/config/dds", glob("config/dds/*.xml")),
        ("share/" + package_name + "/launch", glob("launch/*.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="Home Robot maintainers",
    maintainer_email="maintainers@home-robot.dev",
    description="Node sets, parameters, launch files and a launcher for the home robot.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "launch = home_robot_bringup.launcher:main",
            "demo = home_robot_bringup.demo:main",
        ],
    },
)
