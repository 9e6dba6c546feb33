"""Typed errors of the bring-up package."""


class BringupError(Exception):
    """Base class of bring-up errors."""


class NodeSetError(BringupError):
    """A node-set file is malformed or names an unknown node set."""


class ExecutableNotFound(BringupError):
    """A node's executable is not installed (workspace not built or not sourced?)."""


class NodeNotReady(BringupError):
    """A node did not report readiness before its deadline, or died while starting."""
