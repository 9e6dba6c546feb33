from glob import glob

from setuptools import find_packages, setup

package_name = "decision_maker"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*.yaml")),
        ("share/" + package_name + "/launch", glob("launch/*.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="Home Robot maintainers",
    maintainer_email="maintainers@home-robot.dev",
    description="The brain: command inputs, scenario library, execution engine, simulated robot servers.",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "decision_maker_node = decision_maker.decision_maker_node:main",
            "nl_command_node = decision_maker.nl_command_node:main",
            "cancel_command_node = decision_maker.cancel_command_node:main",
            "mock_nav_server = decision_maker.mock_nav_server:main",
            "mock_grasp_server = decision_maker.mock_grasp_server:main",
            "audio_command_node = decision_maker.audio_command_node:main",
            "plan_command = decision_maker.plan_command:main",
        ]
    },
)
