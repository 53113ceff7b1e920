"""The daemon's targets part follows the store: the active model's id, from any thread, until detached."""

from __future__ import annotations

import threading
from pathlib import Path

from comp_daemon.daemon.targets import Targets
from comp_daemon.robot.description import load_robot
from comp_daemon.service.config import CompensationSettings
from comp_daemon.service.store import ModelDraft, Store


def test_the_active_model_is_followed_from_the_store_until_detached(tmp_path: Path) -> None:
    with Store(tmp_path / "s.sqlite3") as store:
        targets = Targets(load_robot("kr210"), CompensationSettings())
        targets.attach(store)
        assert targets.active_model_id is None and targets.current() is None
        first = store.add_model(ModelDraft("nominal", None, {}, {}, None))
        second = store.add_model(ModelDraft("nominal", None, {}, {}, None))
        store.activate_model(first.id)
        assert targets.active_model_id == first.id
        worker = threading.Thread(target=store.activate_model, args=(second.id,))  # a job's thread
        worker.start()
        worker.join()
        assert targets.active_model_id == second.id
        targets.detach()
        store.activate_model(first.id)
        assert targets.active_model_id == second.id  # no longer listening
