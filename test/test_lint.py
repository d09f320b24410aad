"""The tree passes `ruff check` with the repository's ruff.toml (ruff is pinned in requirements.txt)."""
import pathlib
import subprocess

REPO = pathlib.Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing():
    # Not a skip when ruff is missing: requirements.txt pins it, so a missing ruff is a broken environment.
    from ruff import find_ruff_bin
    result = subprocess.run([find_ruff_bin(), 'check', '--no-cache', '--output-format', 'concise', str(REPO)],
                            cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, f'ruff check found problems (config: ruff.toml):\n{result.stdout}{result.stderr}'


def test_ruff_config_is_the_repository_one():
    # The findings above are only meaningful with the written-down style choices, not ruff's defaults.
    config = (REPO / 'ruff.toml').read_text()
    assert 'line-length = 120' in config
    assert "inline-quotes = 'single'" in config
