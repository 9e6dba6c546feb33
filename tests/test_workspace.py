"""The colcon workspace itself: package manifests, install layout, the minimal nav2_msgs / tf2_msgs guard."""

import glob
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGES = sorted(os.path.dirname(p) for p in glob.glob(os.path.join(ROOT, "src", "*", "package.xml")))


def test_every_package_has_a_standard_manifest():
    names = []
    for pkg in PACKAGES:
        root = ET.parse(os.path.join(pkg, "package.xml")).getroot()
        assert root.get("format") == "3"
        name = root.findtext("name")
        names.append(name)
        assert name == os.path.basename(pkg)
        build_type = root.find("export/build_type").text
        assert build_type in ("ament_python", "ament_cmake")
        if build_type == "ament_python":
            assert os.path.isfile(os.path.join(pkg, "resource", name)), f"{name}: resource marker missing"
            assert f"$base/lib/{name}" in open(os.path.join(pkg, "setup.cfg")).read(), f"{name}: ros2 run layout"
        email = root.find("maintainer").get("email")
        assert "@" in email and "." in email.split("@")[1]
    assert {"decision_maker", "decision_maker_interfaces", "object_query", "object_query_interfaces", "nav2_msgs",
            "home_robot_bringup", "home_robot_ros", "semantic_gs_slam", "semantic_gs_slam_ros"} <= set(names)


def test_slam_core_package_does_not_depend_on_ros():
    root = ET.parse(os.path.join(ROOT, "src", "semantic_gs_slam", "package.xml")).getroot()
    deps = {e.text for e in root if e.tag.endswith("depend")}
    assert not deps & {"rclpy", "std_msgs", "sensor_msgs"}


def test_action_clients_are_the_race_free_one():
    """Every action client is home_robot_ros.actions.ActionClient (rclpy's loses early replies: ros2/rclpy#1123),
    and every package that uses it declares the dependency."""
    offenders, undeclared = [], []
    for path in glob.glob(os.path.join(ROOT, "src", "**", "*.py"), recursive=True) + \
            glob.glob(os.path.join(ROOT, "bench", "*.py")):
        text = open(path).read()
        rel = os.path.relpath(path, ROOT)
        if rel.startswith(os.path.join("src", "home_robot_ros")):
            continue
        if "from rclpy.action import ActionClient" in text or "rclpy.action.ActionClient(" in text:
            offenders.append(rel)
        if "home_robot_ros.actions" in text and rel.startswith("src") and "/test/" not in rel:
            manifest = os.path.join(ROOT, *rel.split(os.sep)[:2], "package.xml")
            if "<exec_depend>home_robot_ros</exec_depend>" not in open(manifest).read():
                undeclared.append(rel)
    assert not offenders, f"use home_robot_ros.actions.ActionClient in {offenders}"
    assert not undeclared, f"add <exec_depend>home_robot_ros</exec_depend> to the package of {undeclared}"


def test_entry_points_follow_ros2_run_layout():
    from home_robot_bringup.nodeset import find_executable

    for pkg, exe in [("object_query", "object_query_server"), ("object_query", "object_query_client"),
                     ("home_robot_bringup", "launch"), ("home_robot_bringup", "demo")]:
        path = find_executable(pkg, exe)
        assert path.endswith(os.path.join("lib", pkg, exe))


def _configure_vendored(tmp_path, ament_prefix_path: str, name: str = "nav2_msgs") -> subprocess.CompletedProcess:
    env = {**os.environ, "AMENT_PREFIX_PATH": ament_prefix_path}
    return subprocess.run(
        ["cmake", "-S", os.path.join(ROOT, "src", name), "-B", str(tmp_path / "build"),
         f"-DCMAKE_INSTALL_PREFIX={tmp_path / 'install'}", f"-DPython3_EXECUTABLE={sys.executable}",
         "-DBUILD_TESTING=OFF"],
        env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.skipif(shutil.which("cmake") is None, reason="cmake not installed")
@pytest.mark.parametrize("name", ["nav2_msgs", "tf2_msgs"])
def test_minimal_vendored_interfaces_never_shadow_a_real_one(tmp_path, name):
    """With the package already installed (a system Nav2 / ROS 2), ours configures to an empty install."""
    system = tmp_path / "opt_ros"
    marker = system / "share" / "ament_index" / "resource_index" / "packages" / name
    marker.parent.mkdir(parents=True)
    marker.write_text("")
    res = _configure_vendored(tmp_path, f"{system}:{os.environ.get('AMENT_PREFIX_PATH', '')}", name)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "installs nothing" in res.stderr
    subprocess.run(["cmake", "--build", str(tmp_path / "build")], check=True, capture_output=True, timeout=300)
    subprocess.run(["cmake", "--install", str(tmp_path / "build")], check=True, capture_output=True, timeout=300)
    installed = [p for p in glob.glob(str(tmp_path / "install" / "**"), recursive=True) if os.path.isfile(p)]
    assert installed == []


def test_minimal_nav2_msgs_is_the_jazzy_definition():
    from nav2_msgs.action import NavigateToPose

    goal, result, feedback = NavigateToPose.Goal(), NavigateToPose.Result(), NavigateToPose.Feedback()
    assert set(goal.get_fields_and_field_types()) == {"pose", "behavior_tree"}
    assert result.get_fields_and_field_types() == {"error_code": "uint16", "error_msg": "string"}
    assert feedback.get_fields_and_field_types() == {
        "current_pose": "geometry_msgs/PoseStamped", "navigation_time": "builtin_interfaces/Duration",
        "estimated_time_remaining": "builtin_interfaces/Duration", "number_of_recoveries": "int16",
        "distance_remaining": "float"}


def test_minimal_tf2_msgs_is_the_jazzy_definition():
    from tf2_msgs.msg import TFMessage

    assert TFMessage.get_fields_and_field_types() == {"transforms": "sequence<geometry_msgs/TransformStamped>"}
