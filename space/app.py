"""The SurfSplat app as a Hugging Face Space (sdk: gradio): the same page as `surfsplat app`.

A Space serves the app on 0.0.0.0:7860 behind its own proxy; uploads are capped and every run's
files are removed an hour after it started (see docs/app.md).
"""

from surfsplat.app import AppConfig, launch

if __name__ == "__main__":
    launch(AppConfig(host="0.0.0.0", port=7860, max_upload_mb=100, keep_minutes=60))
