# One image for every process of a mesh run (see docker-compose.yml).
FROM python:3.11-slim
WORKDIR /app
COPY . /app
RUN pip install --no-cache-dir .
# zenoh peers listen here; the world's port is what agents connect to
EXPOSE 7447
CMD ["diskf-mesh", "--help"]
