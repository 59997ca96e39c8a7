"""docs/configs.md against the configs it describes: every config group, option, key and default it names
exists with that value in neuralsurf/configs (as composed by Hydra), and every option and setting there is
named in it."""

import math
import re
from pathlib import Path

import pytest
import yaml
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "neuralsurf" / "configs"
DOC = (REPO / "docs" / "configs.md").read_text()
GROUP_TABLES = ("data", "model", "observation", "experiment", "suite", "scene", "method")
"""Groups with a table in the doc: one row per option."""


def composed(config_name: str, overrides: list[str]) -> dict:
    """The composed config as plain data, interpolations left as written (`${data_root}`)."""
    with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
        return OmegaConf.to_container(compose(config_name=config_name, overrides=overrides), resolve=False)


def section(title: str) -> str:
    """The doc's text under the heading `title` (any level), up to the next heading."""
    match = re.search(rf"^#+ {re.escape(title)}\n(.*?)(?=^#+ |\Z)", DOC, re.MULTILINE | re.DOTALL)
    assert match, f"docs/configs.md has no section {title!r}"
    return match.group(1)


def table(title: str) -> list[list[str]]:
    """The cells of each body row of the first table under `title`."""
    rows = [line for line in section(title).splitlines() if line.startswith("|")][2:]
    return [[cell.strip() for cell in re.split(r"(?<!\\)\|", row.strip().strip("|"))] for row in rows]


def outside_brackets(text: str) -> str:
    """`text` without what stands inside (), {} or []."""
    depth, kept = 0, []
    for char in text:
        depth += char in "({["
        if depth == 0:
            kept.append(char)
        depth -= char in ")}]"
    return "".join(kept)


def option_names(cell: str) -> list[str]:
    """The options a table row names in its first cell: `a`, `b`."""
    return re.findall(r"`(\w+)`", cell)


NUMBER = r"-?(?:\d{1,3}(?:,\d{3})+|\d+(?:\.\d+)?(?:e-?\d+)?)(?:/\d+)?"


def doc_value(text: str):
    """The default a doc gives after a key ("(1,024)", "(null: ...)", "(`ply`)", " 8,"), or ... when
    there is none to check ("(Gaussian std, ...)", a list of choices)."""
    text = text.strip()
    text = text.removeprefix("(")
    match = re.match(rf"(true|false|null)\b|({NUMBER})(?=$|[\s;:,)])|`([^`|]+)`(?=\s*[;:)]|\s*$)|(\[[^\]]*\])", text)
    if not match:
        return ...
    word, number, quoted, listed = match.groups()
    if word:
        return {"true": True, "false": False, "null": None}[word]
    if number:
        number = number.replace(",", "")
        if "/" in number:
            top, bottom = number.split("/")
            return float(top) / float(bottom)
        return float(number)
    return yaml.safe_load(listed) if listed else quoted


def choices(text: str) -> list[str] | None:
    """The values of a "(`a` \\| `b` \\| `c`)" after a key, or None."""
    match = re.match(r"\s*\((`[^`]+`(?:\s*\\\|\s*`[^`]+`)+)", text)
    return re.findall(r"`([^`]+)`", match.group(1)) if match else None


def same(doc, actual) -> bool:
    if isinstance(doc, float) and isinstance(actual, (int, float)) and not isinstance(actual, bool):
        return math.isclose(doc, actual, rel_tol=1e-9)
    return doc == actual


def find(config: dict, key: str, nested: bool):
    """(True, value) of `key` (dotted: a path; `a.*`: that `a` exists) in `config`, searched through nested
    dicts too when `nested`; else (False, None)."""
    parts = key.removesuffix(".*").split(".")
    value = config
    for part in parts:
        if not isinstance(value, dict) or part not in value:
            break
        value = value[part]
    else:
        return True, value
    if nested and len(parts) == 1:
        for item in config.values():
            if isinstance(item, dict):
                found, value = find(item, key, True)
                if found:
                    return True, value
    return False, None


def check_keys(text: str, config: dict, where: str, *, bare: bool, nested: bool = False) -> list[str]:
    """Problems with the keys `text` names against `config`: `key` (default) and `key` default pairs, and
    with `bare`, every `key` outside brackets; weights {name value, ...} compared entry by entry."""
    problems = []
    named = set(re.findall(r"`([a-z_][\w.*]*)`\s*(?=\(|\{|-?\d)", text))
    if bare:
        named |= {key for key in re.findall(r"`([a-z_][\w.*]*)`", outside_brackets(text))}
    named = {key for key in named if not key.startswith("neuralsurf.") and key not in options("experiment")}
    for key in sorted(named):
        found, actual = find(config, key, nested)
        if not found:
            problems.append(f"{where}: `{key}` is not a key of the config")
            continue
        for after in re.findall(rf"`{re.escape(key)}`(\s*(?:\([^)]*\)?|{NUMBER}))", text):
            listed = choices(after)
            if listed and str(actual) not in listed:
                problems.append(f"{where}: `{key}` is {actual!r}, not one of the doc's {listed}")
            value = doc_value(after)
            if value is not ... and not same(value, actual):
                problems.append(f"{where}: `{key}` is {actual!r} in the config, {value!r} in the doc")
        weights = re.search(rf"`{re.escape(key)}`\s*\{{([^}}]*)\}}", text)
        if weights and isinstance(actual, dict):
            for name, value in re.findall(rf"(\w+) ({NUMBER})", weights.group(1)):
                if not same(doc_value(value), actual.get(name)):
                    problems.append(f"{where}: `{key}.{name}` is {actual.get(name)!r} in the config, {value} in the doc")
    return problems


def options(group: str) -> set[str]:
    return {path.stem for path in (CONFIGS / group).glob("*.yaml")}


@pytest.mark.parametrize("group", GROUP_TABLES)
def test_each_option_of_a_group_has_one_row_and_each_row_names_an_option(group):
    title = {"suite": "suite", "scene": "scene", "method": "method"}.get(group, group)
    named = [name for row in table(title) for name in option_names(row[0])]
    assert sorted(set(named)) == sorted(named), f"{group}: a row is there twice"
    assert set(named) == options(group), (f"docs/configs.md's {group} table: missing "
                                          f"{sorted(options(group) - set(named))}, not configs "
                                          f"{sorted(set(named) - options(group))}")


def test_every_config_group_is_named():
    groups = {path.name for path in CONFIGS.iterdir() if path.is_dir() and not path.name.startswith("_")}
    missing = [group for group in groups if not re.search(rf"^#+ .*\b{group}\b", DOC, re.MULTILINE)]
    assert not missing, f"no heading names the config group(s) {missing}"


def test_data_observation_and_model_keys_and_defaults():
    problems = []
    for row in table("data"):
        for name in option_names(row[0]):
            config = composed("train", ["~experiment", f"data={name}"])["data"]
            if not row[2].startswith("as "):
                problems += check_keys(row[2], config, f"data={name}", bare=True)
    for row in table("observation"):
        name, entry = option_names(row[0])[0], re.match(r"`(\w+):", row[1]).group(1)
        config = composed("train", ["~experiment", f"observation={name}"])["observation"][entry]
        problems += check_keys(row[2], config, f"observation={name}", bare=True)
    for row in table("model"):
        name = option_names(row[0])[0]
        problems += check_keys(row[1], composed("train", ["~experiment", f"model={name}"])["model"],
                               f"model={name}", bare=False, nested=True)
    assert not problems, "\n".join(problems)


def test_data_feeds_and_experiment_observations():
    """The data table's feeds column is each data config's `feeds`; the experiment table's observation column
    names the observations each experiment selects."""
    problems = []
    for row in table("data"):
        for name in option_names(row[0]):
            feeds = composed("train", ["~experiment", f"data={name}"])["data"]["feeds"]
            if option_names(row[3]) != feeds:
                problems.append(f"data={name} feeds {feeds}, the doc says {option_names(row[3])}")
    for row in table("experiment"):
        for name in option_names(row[0]):
            entries = set(composed("train", [f"experiment={name}"])["observation"])
            documented = {key for option in option_names(row[2])
                          for key in yaml.safe_load((CONFIGS / "observation" / f"{option}.yaml").read_text())}
            if not entries <= documented:
                problems.append(f"experiment={name} selects {sorted(entries)}, the doc says {option_names(row[2])}")
    assert not problems, "\n".join(problems)


def test_method_keys_and_defaults():
    methods = composed("evaluate", [])["method"]
    problems = []
    for row in table("method"):
        for name in option_names(row[0]):
            if not row[2].startswith("as "):
                problems += check_keys(row[2], methods[name], f"method.{name}", bare=True)
    assert not problems, "\n".join(problems)


def test_optimizer_trainer_extract_and_score_keys_and_defaults():
    problems = []
    bullets = re.findall(r"^- (`[^`]+`.*?)(?=^- |\Z)", section("optimizer, trainer, extract"), re.MULTILINE | re.DOTALL)
    for bullet in bullets:
        head = re.match(r"`(\w+)(?:: (\w+))?`", bullet)
        group, option = head.groups()
        if option:
            config = composed("train", ["~experiment", f"{group}={option}"])[group]
            body = bullet[head.end():]
            for experiment in set(re.findall(r"`(\w+)`", body)) & options("experiment"):  # options it sets
                config = {**composed("train", [f"experiment={experiment}"])[group], **config}
            problems += check_keys(body, config, f"{group}={option}", bare=True)
            missing = [key for key in config if not key.startswith("_") and f"`{key}`" not in body]
            problems += [f"{group}={option}: `{key}` is not named" for key in missing]
        else:  # `score` of the learned-prior experiments
            config = composed("train", ["experiment=shapes_deepsdf"])[group]
            keys = set(re.findall(r"`(\w+)`", bullet)) - {group}
            problems += [f"{group}: `{key}` is not a key of experiment=shapes_deepsdf's" for key in keys
                         if key not in config]
            problems += check_keys(bullet[head.end():], config, group, bare=False)
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("config_name", ["train", "evaluate"])
def test_top_level_keys(config_name):
    where = {"train": "Overriding", "evaluate": "evaluate.py: suite, scene, method"}[config_name]
    text = re.search(r"Top-level keys[^:]*:(.*?)(?:\. [A-Z]|\n\n)", section(where), re.DOTALL).group(1)
    primary = yaml.safe_load((CONFIGS / f"{config_name}.yaml").read_text())
    keys = [key for key in primary if key not in ("defaults", "hydra")]
    named = set(re.findall(r"`(\w+)`", outside_brackets(text)))
    assert named <= set(keys), f"{config_name}.yaml has no {sorted(named - set(keys))}"
    assert set(keys) <= named, f"docs/configs.md does not name {config_name}.yaml's {sorted(set(keys) - named)}"
    problems = check_keys(text, primary, config_name, bare=False)
    assert not problems, "\n".join(problems)


def test_suites_name_their_scenes_methods_and_settings():
    problems = []
    for row in table("suite"):
        name = option_names(row[0])[0]
        config = composed("evaluate", [f"suite={name}"])
        like = re.match(r"as `(\w+)`", row[1])
        if like:  # the same rows as another suite
            other = composed("evaluate", [f"suite={like.group(1)}"])
            if (config["scenes"], config["methods"]) != (other["scenes"], other["methods"]):
                problems.append(f"suite={name}: not the scenes and methods of suite={like.group(1)}")
            continue
        scenes_text, methods_text = outside_brackets(row[1]).split(" x ", 1)
        scenes = [s.strip() for s in re.split(r",", scenes_text) if s.strip()]
        methods = [m.strip() for m in re.split(r"[;:]", methods_text)[0].split(",") if m.strip()]
        if scenes != list(config["scenes"]):
            problems.append(f"suite={name}: scenes {config['scenes']}, the doc says {scenes}")
        if methods != list(config["methods"]):
            problems.append(f"suite={name}: methods {config['methods']}, the doc says {methods}")
        for method, settings in re.findall(r"(\w+) \(([^)]*)\)", row[1]):
            if method not in config["method"]:
                continue
            steps = re.search(r"([\d,]+) steps", settings)
            if steps and int(steps.group(1).replace(",", "")) != config["method"][method]["trainer"]["steps"]:
                problems.append(f"suite={name}: {method} takes {config['method'][method]['trainer']['steps']} "
                                f"steps, the doc says {steps.group(1)}")
            cube = re.search(r"(\d+)\^3", settings)
            if cube and int(cube.group(1)) != config["method"][method]["extract"]["resolution"]:
                problems.append(f"suite={name}: {method} extracts at {config['method'][method]['extract']}")
    assert not problems, "\n".join(problems)


EXPERIMENT_FIGURES = {
    r"([\d,]+) steps": ("trainer", "steps"),
    r"(\d+)-level": ("model", "encoding", "levels"),
    r"(\d+)\^3": ("extract", "resolution"),
    r"truncation ([\d.]+)": ("observation", "rays", "truncation"),
    r"([\d,]+) rays a step": ("observation", "rays", "n_rays"),
    r"up to ([\d,]+)": ("model", "encoding", "max_resolution"),
}
"""Figures an experiment's row states -> where its composed config holds them."""


def test_experiments_state_their_settings():
    problems = []
    for row in table("experiment"):
        for name in option_names(row[0]):
            config = composed("train", [f"experiment={name}"])
            for pattern, path in EXPERIMENT_FIGURES.items():
                for figure in re.findall(pattern, row[1]):
                    actual = config
                    for part in path:
                        actual = actual[part]
                    if float(figure.replace(",", "")) != actual:
                        problems.append(f"experiment={name}: {'.'.join(path)} is {actual}, the doc says {figure}")
    assert not problems, "\n".join(problems)


def test_the_checks_catch_a_wrong_default_and_an_unknown_key():
    config = {"steps": 2000, "weights": {"surface": 3.0}, "noise": "kinect"}
    assert check_keys("`steps` (2,000), `weights` {surface 3}, `noise` (`none` \\| `kinect`)", config, "x",
                      bare=True) == []
    problems = check_keys("`steps` (1,500), `weights` {surface 2}, `noise` (`none` \\| `gaussian`), `levels`",
                          config, "x", bare=True)
    assert len(problems) == 4 and any("`levels` is not a key" in p for p in problems)
