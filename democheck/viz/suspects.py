"""Which demos an audit's report shows beside the table, read from the dataset only when the report reaches each:
``Suspects`` (the top of the ranking, every camera) and ``Typical`` (per task, the demo the ranking finds least
suspect, to compare a suspect with)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor

import pandas as pd

from democheck.data.demo import DemoSet, camera_name
from democheck.viz.report import fit_frames


class Suspects(Sequence):
    """The top demos, each read from the dataset when the report reaches it (twenty hub-sized demos held at once
    are gigabytes of frames), with every other camera's pictures (``Demo.extra["cameras"]``, by short name), every
    camera's frames shrunk to the recording's size as they are read (``report.fit_frames``)."""

    def __init__(self, ds: DemoSet, episodes: list[int]):
        self.ds, self.episodes = ds, episodes
        self.others = ds.other_cameras() if ds.has_camera else {}

    def __len__(self) -> int:
        return len(self.episodes)

    def __getitem__(self, i):
        demo = self.ds[int(self.episodes[i])]
        demo.frames = fit_frames(demo.frames)
        if self.others:
            demo.extra["camera"] = camera_name(self.ds.camera)
            demo.extra["cameras"] = {c: fit_frames(v[demo.episode_index].frames) for c, v in self.others.items()}
        return demo

    def __iter__(self):
        """Each demo in turn, the next one read (and shrunk) in a thread while the report writes this one: decoding
        and the report's encoding overlap on two cores."""
        with ThreadPoolExecutor(1) as reader:
            ahead = reader.submit(self.__getitem__, 0) if len(self) else None
            for i in range(len(self)):
                demo = ahead.result()
                ahead = reader.submit(self.__getitem__, i + 1) if i + 1 < len(self) else None
                yield demo


class Typical(Mapping):
    """Per task of the report's suspects, its unflagged demo the ranking finds least suspect (read when the report
    reaches it): what a demo of that task looks like, to compare a suspect with."""

    def __init__(self, ds: DemoSet, table: pd.DataFrame, shown: int):
        self.ds = ds
        clean = table[~table["is_anomaly"].to_numpy(bool)]
        least = clean.loc[clean.groupby("task", sort=False)["suspicion"].idxmin()] if len(clean) else clean
        tasks = set(table.head(shown)["task"])
        self.episodes = {t: int(e) for t, e in zip(least["task"], least["episode_index"]) if t in tasks}

    def __len__(self) -> int:
        return len(self.episodes)

    def __iter__(self):
        return iter(self.episodes)

    def __getitem__(self, task):
        return self.ds[self.episodes[task]]
