FROM python:3.11-slim
RUN apt-get update && apt-get install -y --no-install-recommends libgl1 libglib2.0-0 \
    && rm -rf /var/lib/apt/lists/*
RUN useradd --create-home recslam
WORKDIR /app
COPY pyproject.toml requirements.lock README.md ./
COPY recslam recslam
COPY common common
COPY services services
COPY dashboard dashboard
RUN pip install --no-cache-dir -c requirements.lock .
USER recslam
ENTRYPOINT []
CMD ["recslam", "--help"]
