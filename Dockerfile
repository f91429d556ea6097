# One image for every recslam service (cloud, edge, robot, dataset).
# The entrypoint (docker/entrypoint.sh) starts as root only to apply $NETEM with tc and to hand
# fresh (empty) bind-mounted folders to the user "recslam", then drops to that unprivileged
# user (setpriv) before running the service.
#
# Behind a TLS-intercepting proxy or a private index (docs/deployment.md, "Building behind a
# proxy"): put the proxy's CA certificate(s) as *.crt into docker/ca-certificates/ and/or pass
#   --build-arg PIP_INDEX=https://... --build-arg PIP_EXTRA_INDEX=... --build-arg PIP_TRUSTED=host
# (compose passes the same names from the environment).
FROM python:3.11-slim
# iproute2: tc for $NETEM. No libgl1 / libglib2.0-0: opencv-python-headless, pycolmap and
# gtsam link neither (checked on the built image: `python -c "import cv2, pycolmap, gtsam"`).
RUN apt-get update && apt-get install -y --no-install-recommends iproute2 \
    && rm -rf /var/lib/apt/lists/*
RUN useradd --create-home --uid 1000 recslam \
    && mkdir -p /state /results /datasets && chown recslam:recslam /state /results /datasets
# Extra CA certificates (docker/ca-certificates/*.crt; the folder holds only a README by
# default) join the system store, which pip then uses instead of its own bundle.
COPY docker/ca-certificates/ /usr/local/share/ca-certificates/recslam/
RUN if ls /usr/local/share/ca-certificates/recslam/*.crt >/dev/null 2>&1; then \
        update-ca-certificates; fi
WORKDIR /app
COPY pyproject.toml requirements.lock README.md ./
COPY recslam recslam
COPY common common
COPY services services
COPY dashboard dashboard
COPY lab lab
COPY sim sim
ARG PIP_INDEX=""
ARG PIP_EXTRA_INDEX=""
ARG PIP_TRUSTED=""
RUN set -e; \
    if ls /usr/local/share/ca-certificates/recslam/*.crt >/dev/null 2>&1; then \
        export PIP_CERT=/etc/ssl/certs/ca-certificates.crt; fi; \
    pip install --no-cache-dir --disable-pip-version-check \
        ${PIP_INDEX:+--index-url "$PIP_INDEX"} \
        ${PIP_EXTRA_INDEX:+--extra-index-url "$PIP_EXTRA_INDEX"} \
        ${PIP_TRUSTED:+--trusted-host "$PIP_TRUSTED"} \
        -c requirements.lock . \
    && python -c "import cv2, gtsam, pycolmap"
COPY docker/entrypoint.sh /usr/local/bin/recslam-entrypoint
RUN chmod 0755 /usr/local/bin/recslam-entrypoint
ENV PYTHONUNBUFFERED=1
ENTRYPOINT ["recslam-entrypoint"]
CMD ["recslam", "--help"]
