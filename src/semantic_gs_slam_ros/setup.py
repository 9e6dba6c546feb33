from setuptools import find_packages, setup

package_name = "semantic_gs_slam_ros"

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
    description="ROS 2 streaming server and client around the semantic_gs_slam engine.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "run_gs_slam_server = semantic_gs_slam_ros.run_gs_slam_server:main",
            "run_gs_slam_client = semantic_gs_slam_ros.run_gs_slam_client:main",
        ],
    },
)
