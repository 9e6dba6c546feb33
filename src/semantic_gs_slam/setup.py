from setuptools import find_packages, setup

package_name = "semantic_gs_slam"

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
    description="Semantic Gaussian-splatting RGB-D SLAM engine (pure Python/PyTorch library, no ROS).",
    license="Apache-2.0",
    entry_points={"console_scripts": [
        "semantic_gs_slam_run = semantic_gs_slam.run:main",
        "semantic_gs_slam_synth = semantic_gs_slam.synthetic.scenes:main",
    ]},
)
