from setuptools import find_packages, setup

package_name = "home_robot_web"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={package_name: ["static/*"]},
    include_package_data=True,
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="Home Robot maintainers",
    maintainer_email="maintainers@home-robot.dev",
    description="The robot's web page: commands, live status, STOP, object memory, 3-D map; token when exposed.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "web_ui_node = home_robot_web.web_ui_node:main",
        ]
    },
)
