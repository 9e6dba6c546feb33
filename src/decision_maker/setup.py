from setuptools import find_packages, setup

package_name = "decision_maker"

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
    description="The brain: command inputs, scenario library, execution engine, simulated robot servers.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "audio_command_node = decision_maker.audio_command_node:main",
        ]
    },
)
