"""ament_python build of dpv_sensor: executables land in lib/dpv_sensor so `ros2 run` finds them."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'dpv_sensor'

# Console tools, each runnable as `ros2 run dpv_sensor <name>`.
TOOLS = {
    'node': 'dpv_sensor.ros.entry:console_main',
    'evaluate': 'dpv_sensor.tools.evaluate:main',
    'fuse': 'dpv_sensor.tools.fuse:main',
    'train': 'dpv_sensor.tools.train:main',
    'adapt': 'dpv_sensor.tools.adapt:main',
    'bag': 'dpv_sensor.tools.bag:main',
    'soak': 'dpv_sensor.tools.soak:main',
    'demo': 'dpv_sensor.tools.demo:main',
    'bench': 'dpv_sensor.tools.bench:main',
    'calibrate': 'dpv_sensor.tools.calibrate:main',
    'calibrate_mount': 'dpv_sensor.tools.calibrate_mount:main',
    'export_onnx': 'dpv_sensor.tools.export_onnx:main',
}

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={PACKAGE: ['weights/*.safetensors']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml') + glob('config/*.xml')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.launch.py')),
        ('share/' + PACKAGE + '/weights', glob('dpv_sensor/weights/*.safetensors')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='dpv_sensor maintainers',
    maintainer_email='dpv-sensor-dev@example.org',
    description='Virtual RGB-D camera from monocular video and odometry (depth probability volumes).',
    license='Apache-2.0',
    entry_points={'console_scripts': [f'{name} = {target}' for name, target in TOOLS.items()]},
)
