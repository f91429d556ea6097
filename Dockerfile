# One image for every recslam service (cloud, edge, robot, dataset).
# The entrypoint (docker/entrypoint.sh) starts as root only to apply $NETEM with tc, then drops
# to the unprivileged user "recslam" (setpriv) before running the service.
FROM python:3.11-slim
RUN apt-get update && apt-get install -y --no-install-recommends libgl1 libglib2.0-0 iproute2 \
    && rm -rf /var/lib/apt/lists/*
RUN useradd --create-home --uid 1000 recslam \
    && mkdir -p /state /results /datasets && chown recslam:recslam /state /results
WORKDIR /app
COPY pyproject.toml requirements.lock README.md ./
COPY recslam recslam
COPY common common
COPY services services
COPY dashboard dashboard
COPY lab lab
RUN pip install --no-cache-dir -c requirements.lock .
COPY docker/entrypoint.sh /usr/local/bin/recslam-entrypoint
RUN chmod 0755 /usr/local/bin/recslam-entrypoint
ENV PYTHONUNBUFFERED=1
ENTRYPOINT ["recslam-entrypoint"]
CMD ["recslam", "--help"]
