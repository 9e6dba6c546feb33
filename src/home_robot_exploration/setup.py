from setuptools import find_packages, setup

package_name = "home_robot_exploration"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="Home Robot maintainers",
    maintainer_email="maintainers@home-robot.dev",
    description="Stage 0: simulated RGB-D camera, occupancy grid from depth, frontier explorer.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "sim_camera_node = home_robot_exploration.sim_camera_node:main",
            "explorer_node = home_robot_exploration.explorer_node:main",
            "demo_explore = home_robot_exploration.demo_explore:main",
            "live_view_node = home_robot_exploration.live_view_node:main",
        ]
    },
)
