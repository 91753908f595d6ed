import inspect

import temoto
import temoto.actions
import temoto.errors


def test_every_exception_in_errors_is_exported() -> None:
    classes = {
        name
        for name, obj in vars(temoto.errors).items()
        if inspect.isclass(obj)
        and issubclass(obj, BaseException)
        and obj.__module__ == "temoto.errors"
    }
    assert classes <= set(temoto.errors.__all__)


def test_every_error_is_a_temoto_error_except_stop_requested() -> None:
    for name in temoto.errors.__all__:
        obj = getattr(temoto.errors, name)
        if inspect.isclass(obj) and issubclass(obj, BaseException) and name != "StopRequested":
            assert issubclass(obj, temoto.errors.TemotoError), name
    assert not issubclass(temoto.errors.StopRequested, Exception)


def test_config_errors_are_value_errors_and_carry_file_and_path() -> None:
    err = temoto.errors.GraphDefinitionError("bad", file="g.json", path="actions[1].name")
    assert isinstance(err, ValueError)
    assert str(err) == "g.json: actions[1].name: bad"
    assert (err.file, err.path, err.reason) == ("g.json", "actions[1].name", "bad")


def test_errors_survive_pickling_and_become_records() -> None:
    import pickle

    err = temoto.errors.GraphDefinitionError("bad", file="g.json", path="x")
    again = pickle.loads(pickle.dumps(err))
    assert type(again) is type(err)
    assert str(again) == str(err)
    assert again.path == "x"
    try:
        try:
            raise ValueError("root cause")
        except ValueError as cause:
            raise temoto.errors.ActionError("failed", graph="g", node="A_0") from cause
    except temoto.errors.ActionError as chained:
        records = chained.to_records()
    assert [r.type for r in records] == ["ActionError", "ValueError"]
    rebuilt = temoto.errors.RemoteError.from_records(records)
    assert "failed" in str(rebuilt)
    assert "root cause" in str(rebuilt.__cause__)


def test_subpackage_all_names_exist() -> None:
    for module in (temoto, temoto.actions, temoto.errors):
        for name in module.__all__:
            assert hasattr(module, name), f"{module.__name__}.{name}"
