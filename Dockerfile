# The SurfSplat browser app on CPU: docker build -t surfsplat-app . && docker run -p 7860:7860 surfsplat-app
FROM python:3.11-slim

# ffmpeg's libraries come with imageio-ffmpeg; libgl and libglib serve pycolmap's and OpenCV-style wheels.
RUN apt-get update && apt-get install -y --no-install-recommends libgl1 libglib2.0-0 \
    && rm -rf /var/lib/apt/lists/*

RUN useradd --create-home app
WORKDIR /home/app/surfsplat
COPY --chown=app . .
# The README's install command, with the app extra: CPU PyTorch first, then the package.
RUN pip install --no-cache-dir --extra-index-url https://download.pytorch.org/whl/cpu torch==2.13.0 -e ".[app]"

USER app
ENV GRADIO_ANALYTICS_ENABLED=False
EXPOSE 7860
CMD ["surfsplat", "app", "--host", "0.0.0.0", "--port", "7860"]
