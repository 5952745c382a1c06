# The recal gateway daemon. On a gateway: map the serial devices, mount a volume for recordings
# and checkpoints, and use host networking (or publish the Zenoh port) so peers/routers reach it:
#   docker build -t recal .
#   docker run --device /dev/ttyUSB0 -v /srv/recal:/var/lib/recal --network host recal \
#       run --port /dev/ttyUSB0 --sensor-id wrist --config /etc/recal/gateway.toml
# configs/gateway.toml writes recordings to /var/lib/recal/recordings and checkpoints to
# /var/lib/recal/checkpoints, i.e. into the volume, so both outlive the container.
FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY service ./service
COPY configs /etc/recal
RUN pip install --no-cache-dir .
RUN mkdir -p /var/lib/recal/recordings /var/lib/recal/checkpoints
VOLUME ["/var/lib/recal"]
WORKDIR /var/lib/recal
ENTRYPOINT ["recal"]
CMD ["run", "--config", "/etc/recal/gateway.toml"]
