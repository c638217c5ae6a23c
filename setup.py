"""ament_python set-up of cdpr_dynamics (also pip-installable into a venv)."""
from glob import glob

from setuptools import find_packages, setup

package_name = 'cdpr_dynamics'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config',
         sorted(glob('config/*.yaml') + glob('config/*.rviz') + glob('config/*.json'))),
        ('share/' + package_name + '/launch', glob('launch/*.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='cdpr_dynamics maintainers',
    maintainer_email='maintainers@cdpr-dynamics.invalid',
    description='Live vibration prediction for cable-driven parallel robots (ROS 2 Jazzy).',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'dynamics_node = cdpr_dynamics.ros.process:main',
            'cdpr_analyze = cdpr_dynamics.cli:cdpr_analyze',
            'cdpr_bench = cdpr_dynamics.cli:cdpr_bench',
            'cdpr_record = cdpr_dynamics.cli:cdpr_record',
            'cdpr_demo = cdpr_dynamics.cli:cdpr_demo',
            'cdpr_tradeoff = cdpr_dynamics.cli:cdpr_tradeoff',
            'cdpr_estimate_table = cdpr_dynamics.cli:cdpr_estimate_table',
            'cdpr_replay = cdpr_dynamics.cli:cdpr_replay',
            'cdpr_workspace = cdpr_dynamics.cli:cdpr_workspace',
            'cdpr_calibrate = cdpr_dynamics.cli:cdpr_calibrate',
        ],
    },
)
