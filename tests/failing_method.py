"""A method that always raises, for the tests of failed evaluation rows (importable: pytest puts tests/ on
sys.path)."""


def always_fails(scene, *, message: str = "this method always fails", **_) -> None:
    raise RuntimeError(message)
