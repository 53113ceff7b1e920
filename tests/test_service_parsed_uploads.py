"""One parse per upload: a fit job of a just-uploaded data set takes the data set as the upload
parsed it, not its stored CSV parsed again; the campaign header's one sniffer."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import httpx
import pytest
from service_client import job_done
from test_service_api import auth, campaign_csv, make_settings

from comp_daemon.data import readers
from comp_daemon.data.bars import header_kind, sniff_campaign, sniff_campaign_file
from comp_daemon.data.dataset import parse_dataset
from comp_daemon.data.table import Dataset
from comp_daemon.service.api import create_app, open_store
from comp_daemon.service.job_kinds import run_diagnosis, run_fit
from comp_daemon.service.uploads import ParsedDatasets, check_upload


def _quiet(*args: Any, **kwargs: Any) -> None:
    return None


async def test_fit_after_upload_takes_the_parsed_data_set(tmp_path: Path) -> None:
    settings = make_settings(tmp_path, jobs={"workers": 1})
    store = open_store(settings)
    try:
        app = create_app(settings, store)
        async with app.router.lifespan_context(app):
            svc = app.state.svc
            launched: list[tuple[Any, ...]] = []
            launch = svc.runner.launch

            def spy(job: Any, args: tuple[Any, ...]) -> None:
                launched.append(args)
                launch(job, args)

            svc.runner.launch = spy
            transport = httpx.ASGITransport(app=app)
            async with httpx.AsyncClient(transport=transport, base_url="http://cell") as client:
                text = campaign_csv(60)
                up = await client.post(
                    "/api/datasets?name=c",
                    content=text,
                    headers={**auth("engineer"), "Content-Type": "text/csv"},
                )
                assert up.status_code == 201, up.text
                dataset_id = up.json()["id"]
                r = await client.post(
                    "/api/fits",
                    json={"dataset_id": dataset_id, "model": "kinematic"},
                    headers=auth("engineer"),
                )
                assert r.status_code == 202, r.text
                done = await job_done(client, r.json()["id"])
                assert done["state"] == "done", done["error"]
                stored = (
                    await client.get(f"/api/datasets/{dataset_id}/content", headers=auth("viewer"))
                ).text
                d = await client.post(
                    "/api/diagnoses", json={"dataset_id": dataset_id}, headers=auth("engineer")
                )
                assert d.status_code == 202, d.text
                await client.post(f"/api/jobs/{d.json()['id']}/cancel", headers=auth("engineer"))
    finally:
        store.close()
    assert isinstance(launched[1][0], Dataset)  # the diagnosis job too
    data = launched[0][0]
    assert isinstance(data, Dataset), "the fit job was handed the CSV text to parse again"
    again = parse_dataset(stored, source=f"dataset {dataset_id}", min_rows=1)
    assert data == again and data.source == again.source
    assert list(data.row_numbers) == list(again.row_numbers)
    # the same fit as from the stored text, to the bit (but for the solver's clock)
    from_text = run_fit(stored, "kr210", "kinematic", None, dataset_id, progress=_quiet)
    assert _timeless(done["result"]["stats"]) == _timeless(from_text["stats"])


def _timeless(stats: dict[str, Any]) -> str:
    plain = json.loads(json.dumps(stats, allow_nan=False))
    del plain["fit"]["solver"]["time_s"]
    return json.dumps(plain, sort_keys=True)


def test_run_fit_of_a_parsed_data_set_calls_no_parser(monkeypatch: pytest.MonkeyPatch) -> None:
    text = campaign_csv(60)
    checked = check_upload(text.encode(), "csv", "c", None, "measurement")
    assert checked.dataset is not None
    parsed = ParsedDatasets()
    parsed.put(7, checked.dataset)
    kept = parsed.get(7, checked.sha256)
    assert kept is not None and kept.source == "dataset 7"

    def refuse(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("the CSV was parsed again")

    monkeypatch.setattr(readers, "parse_dataset", refuse)
    monkeypatch.setattr("comp_daemon.data.dataset.parse_dataset", refuse)
    done = run_fit(kept, "kr210", "kinematic", None, 7, progress=_quiet)
    assert done["stats"]["rows"] == {"fit": 45, "check": 15}
    assert done["artifact"]["data_sha256"] == checked.sha256
    report = run_diagnosis(kept, "kr210", 7, progress=_quiet)["report"]
    assert report["data"] == {"source": "dataset 7", "content_sha256": checked.sha256}


def test_parsed_data_sets_are_keyed_by_content_and_bounded() -> None:
    a = check_upload(campaign_csv(40, seed=1).encode(), "csv", "a", None, "measurement")
    b = check_upload(campaign_csv(40, seed=2).encode(), "csv", "b", None, "measurement")
    assert a.dataset is not None and b.dataset is not None
    parsed = ParsedDatasets(max_rows=60)
    parsed.put(1, a.dataset)
    assert parsed.get(1, b.sha256) is None  # another content under the same id: not the one kept
    parsed.put(2, b.dataset)  # 80 rows > 60: the older goes
    assert parsed.get(1, a.sha256) is None and parsed.get(2, b.sha256) is not None
    parsed.forget(2)
    assert parsed.get(2, b.sha256) is None


def test_an_upload_without_positions_is_not_kept_for_a_fit() -> None:
    targets = "a1,a2,a3,a4,a5,a6\n0,-90,90,0,0,0\n10,-90,90,0,0,0\n"
    checked = check_upload(targets.encode(), "csv", "t", None, "any")
    assert checked.dataset is None  # the job parses the stored text and refuses it as the reader does


@pytest.mark.parametrize(
    ("head", "kind"),
    [
        (b"a1,a2,a3,a4,a5,a6,bar_mm,cx,cy,cz,arc\n1,2", "ballbar"),
        ('\ufeff"a1",a2,a3,a4,a5,a6,"dr_um"\r\n'.encode(), "ballbar"),
        ("a1,a2,a3,a4,a5,a6, placement ,socket,bar_l_mm\n", "crossbar"),
        (b'a1,a2,a3,a4,a5,a6,x,y,z,"note, bar_mm"\n', None),  # a quoted cell is one name
        (b"a1,a2,a3,a4,a5,a6,x,y,z\n", None),
        (b"", None),
    ],
)
def test_one_sniffer_of_the_campaign_header(head: bytes | str, kind: str | None, tmp_path: Path) -> None:
    assert sniff_campaign(head) == kind
    path = tmp_path / "c.csv"
    path.write_bytes(head if isinstance(head, bytes) else head.encode())
    assert sniff_campaign_file(path) == kind
    assert sniff_campaign_file(tmp_path / "missing.csv") is None
    assert header_kind(["bar_mm", "placement"]) == "ballbar"


def test_a_kept_json_upload_is_the_data_set_its_stored_text_gives(monkeypatch: pytest.MonkeyPatch) -> None:
    from comp_daemon.data import table

    rows = [line.split(",") for line in campaign_csv(12).splitlines()]
    header = rows[0]
    records = [{k: c if k == "split" else float(c) for k, c in zip(header, r, strict=True)} for r in rows[1:]]
    checked = check_upload(json.dumps(records).encode(), "json", "j", None, "measurement")
    assert checked.dataset is not None and checked.dataset.row_label == "record"
    parsed = ParsedDatasets()
    parsed.put(3, checked.dataset)
    kept = parsed.get(3, checked.sha256)
    assert kept is not None
    again = parse_dataset(checked.content, source="dataset 3", min_rows=1)
    assert kept == again and kept.row_label == again.row_label == "row"
    assert list(kept.row_numbers) == list(again.row_numbers)

    def no_rendering(dataset: Dataset) -> str:
        raise AssertionError("the canonical CSV was rendered again")

    monkeypatch.setattr(table, "_render_csv", no_rendering)
    import pickle

    arrived = pickle.loads(pickle.dumps(kept))  # as a job's argument reaches the worker
    assert arrived.content_sha256 == checked.sha256 and arrived.source == "dataset 3"
