"""Training recipes: every shipped one loads, round-trips through the card's TOML, and the shipped models'
recipes are exactly the options those models were trained with."""

import json
import tomllib
from dataclasses import asdict

import pytest

from democheck import resources
from democheck.errors import DemocheckError
from democheck.petnet.recipe import load_recipe, recipe_toml, training_config


@pytest.mark.parametrize("name", resources.recipe_names("train"))
def test_shipped_recipe_loads_and_round_trips(name, tmp_path):
    tc, resolved = load_recipe(name)
    assert resolved["name"] == name and resolved["source"] == name and resolved["config"] == asdict(tc)
    again = tmp_path / "again.toml"
    again.write_text(recipe_toml(resolved))
    tomllib.loads(again.read_text())
    assert load_recipe(again)[0] == tc


@pytest.mark.parametrize("model, recipe", [("petnet-push-v1", "petnet-push-v1"), ("petnet-push-v2", "petnet-push-v4"),
                                           ("tecnet-push-v1", "tecnet")])
def test_shipped_models_recipe_is_what_they_were_trained_with(model, recipe):
    record = json.loads((resources.shipped_model(model) / "config.json").read_text())["training"]
    assert load_recipe(recipe)[0] == training_config(record)


def test_the_default_recipe_is_the_papers_loss():
    tc, _ = load_recipe()
    assert tc.model_type == "petnet" and tc.regularisers == {} and tc.lr == 5e-4 and tc.steps == 20_000


def test_overrides_and_everyday_options():
    tc, resolved = load_recipe("paper", ["optim.lr=1e-3", "regularisers.task_matching=0.5", "shift=2",
                                         "model.init=''"], steps=10, seed=3)
    assert (tc.lr, tc.regularisers, tc.shift, tc.init, tc.steps, tc.seed) == (1e-3, {"task_matching": 0.5}, 2, None,
                                                                              10, 3)
    assert resolved["set"][0] == "optim.lr=1e-3"
    with pytest.raises(DemocheckError, match="ambiguous|unknown"):
        load_recipe("paper", ["nope=1"])
    record = {**asdict(tc), "a_key_of_another_release": 1}
    assert training_config(record) == tc
