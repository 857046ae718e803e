"""`submit` against a live server: upload a file, follow SSE, write the image."""

from __future__ import annotations

import numpy as np

from nprt.service.__main__ import main
from tests.service.helpers import png_pixels


def test_submit_uploads_file_waits_and_writes_png(live, client, glb_path, tmp_path, capsys):
    out = tmp_path / "out.png"
    rc = main(["submit", str(glb_path), "--server", live.url, "--width", "24", "--height", "16",
               "--spp", "2", "--bounces", "1", "--tile-size", "8", "-o", str(out)])
    assert rc == 0
    job_id = capsys.readouterr().out.strip().splitlines()[-1]
    job = client.get(f"/v1/jobs/{job_id}").json()
    assert job["state"] == "succeeded" and job["settings"]["width"] == 24
    served = png_pixels(client.get(f"/v1/jobs/{job_id}/image.png").content)
    np.testing.assert_array_equal(png_pixels(out.read_bytes()), served)
    assert served.shape == (16, 24, 3)


def test_submit_reports_bad_settings_with_exit_code(live, capsys):
    rc = main(["submit", "forest:tiny", "--server", live.url, "--spp", "0"])
    assert rc == 2
    assert "spp: Input should be greater than or equal to 1" in capsys.readouterr().err
