from setuptools import find_packages, setup

package_name = 'pisc_gym'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/pisc_gym']),
        ('share/pisc_gym', ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='PISC maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-5c3c3dbe.example',
    description=(
        "PISC's rig as Gymnasium environments (swing-up and catch, single and vector) on the"
        ' compiled plant kernel, with the motor, the sensors, the latency and domain'
        ' randomisation; their benchmark and a learning example. No ROS.'
    ),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'pisc_gym_bench = pisc_gym.bench_cli:main',
            'pisc_gym_learn = pisc_gym.learn_cli:main',
            'pisc_gym_catchable = pisc_gym.catchable_cli:main',
        ],
    },
)
